//! Where keys are written in a TOML file, so that errors found after deserialising (an
//! invalid value, a missing key) can name the key's dotted path and its line.

use std::ops::Range;

/// 1-based line of a byte offset.
pub fn line_of(text: &str, offset: usize) -> usize {
    text.as_bytes()[..offset.min(text.len())]
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
        + 1
}

/// Where one key of a TOML document is written.
struct KeySpan {
    /// Dotted path, e.g. `codes.front_side`.
    path: String,
    /// Byte range of the key.
    key: Option<Range<usize>>,
    /// Byte range of its value (a table's header for a table).
    value: Option<Range<usize>>,
}

/// Spans in a TOML document: of the root table's own keys and of every key.
#[derive(Default)]
pub struct KeySpans {
    /// Span of the root table.
    pub root: Option<Range<usize>>,
    keys: Vec<KeySpan>,
}

impl KeySpans {
    /// The spans of a parsed document's root table.
    pub fn of(root: &toml_edit::Table) -> KeySpans {
        let mut out = KeySpans {
            root: root.span(),
            keys: Vec::new(),
        };
        out.walk("", root);
        out
    }

    fn walk(&mut self, prefix: &str, table: &dyn toml_edit::TableLike) {
        for (name, item) in table.iter() {
            let path = if prefix.is_empty() {
                name.to_owned()
            } else {
                format!("{prefix}.{name}")
            };
            self.keys.push(KeySpan {
                path: path.clone(),
                key: table.key(name).and_then(|k| k.span()),
                value: item.span(),
            });
            if let Some(t) = item.as_table_like() {
                self.walk(&path, t);
            } else if let Some(array) = item.as_array_of_tables() {
                // [[name]] tables: `name[i].key`.
                for (i, t) in array.iter().enumerate() {
                    let element = format!("{path}[{i}]");
                    self.keys.push(KeySpan {
                        path: element.clone(),
                        key: None,
                        value: t.span(),
                    });
                    self.walk(&element, t);
                }
            }
        }
    }

    /// The innermost key whose key or value text covers `span`.
    pub fn field_at(&self, span: &Range<usize>) -> Option<String> {
        let covers = |r: &Option<Range<usize>>| {
            r.as_ref()
                .filter(|r| r.start <= span.start && span.end <= r.end.max(r.start + 1))
                .map(|r| r.len())
        };
        self.keys
            .iter()
            .filter_map(|k| Some((covers(&k.key).into_iter().chain(covers(&k.value)).min()?, k)))
            .min_by_key(|&(len, _)| len)
            .map(|(_, k)| k.path.clone())
    }

    /// Line of a field's key, or of its nearest written parent table.
    pub fn line_of(&self, field: &str, text: &str) -> Option<usize> {
        let mut path = field;
        loop {
            if let Some(k) = self.keys.iter().find(|k| k.path == path) {
                let at = k.key.as_ref().or(k.value.as_ref());
                return at.map(|s| line_of(text, s.start));
            }
            path = &path[..path.rfind('.')?];
        }
    }
}
