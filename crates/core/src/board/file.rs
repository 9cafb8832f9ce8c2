//! Board files: a [`Board`] written as TOML, read with [`Board::from_toml_str`],
//! [`Board::load`] or [`Board::resolve`] (the command line's `--board hex600|FILE`).
//!
//! Every key of the file is a field of [`Board`]; unknown keys are errors, and so is any
//! board that breaks a rule of [`Board::validate`]. Errors name the file, the field and its
//! line. Lengths are in millimetres. The built-in board as a file (`rigs/boards/hex600.toml`):
//!
//! ```toml
//! name = "hex600"          # printed on the target and written into outputs
//! pitch = 20.0             # lattice pitch d: (x, y) = d·(q + r/2, (√3/2)·r)
//! radius = 6.0             # circle radius R
//! half_width = 290.0       # a circle sits at every lattice point with |x| ≤ half_width
//! half_height = 230.0      #   and |y| ≤ half_height
//! size = [600.0, 500.0]    # the black board, width and height, centred on the lattice origin
//! ring = [0.45, 0.75]      # marker ring radii, inner and outer, as fractions of R
//! thickness = 10.0         # t in the nominal side transform X = −x_b, Y = y_b, Z = −t
//! marker_spacing = 6       # side marks at (q, r) = (s·i, s·j) whose whole cell is on the board
//!
//! [codes]                  # neighbour k ringed when character k is 1 (bit 0 first)
//! front_center = "011111"
//! back_center = "000111"
//! front_side = "001011"
//! back_side = "001101"
//!
//! # Optional: the measured T_front_back (back-side points into the front frame), replacing
//! # the nominal half turn about y. Axis-angle in radians, translation in millimetres.
//! # [front_back]
//! # rotation = [0.0, 3.14159265358979, 0.0]
//! # translation = [0.0, 0.0, -10.0]
//! ```
//!
//! A board printed on the front only says `sides = 1` (default 2) and has no back: no
//! `codes.back_center`, `codes.back_side`, `thickness` or `[front_back]`; its side marks
//! (`codes.front_side` with `marker_spacing`) are optional (`rigs/boards/hex600-front.toml`).

use super::{Board, InvalidField};
use std::path::{Path, PathBuf};

/// Why a board could not be read: the origin (file path or `<string>`), the field and, where
/// known, the line.
#[derive(Debug, thiserror::Error)]
pub enum BoardError {
    /// The file could not be read.
    #[error("board file {}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
    /// The text is not TOML, or does not have the fields and types of a board file.
    #[error("board file {origin}{}: {message}", at(*line, field.as_deref()))]
    Parse {
        /// File path or `<string>`.
        origin: String,
        /// 1-based line of the offending text.
        line: Option<usize>,
        /// The dotted key at that place, when the error sits on a key or its value.
        field: Option<String>,
        /// What the TOML reader said.
        message: String,
    },
    /// The board breaks a rule of [`Board::validate`].
    #[error("board file {origin}{}: {}", at(*line, Some(&invalid.field)), invalid.message)]
    Invalid {
        /// File path or `<string>`.
        origin: String,
        /// 1-based line of the field's key, when the field is written in the file.
        line: Option<usize>,
        /// The rule broken, with the field to fix.
        invalid: InvalidField,
    },
    /// `--board` named neither a built-in board nor an existing file.
    #[error(
        "board {0:?} is neither a built-in board ({names}) nor a file",
        names = builtin_names()
    )]
    Unknown(String),
    /// A file's board value is neither a built-in board nor a board file inside the file's
    /// folder: the file, the value's JSON path and what is wrong.
    #[error(transparent)]
    Named(crate::ValidationError),
}

impl BoardError {
    /// The dotted field the error is about, if it is about one.
    pub fn field(&self) -> Option<&str> {
        match self {
            BoardError::Parse { field, .. } => field.as_deref(),
            BoardError::Invalid { invalid, .. } => Some(&invalid.field),
            BoardError::Named(e) => Some(&e.at),
            BoardError::Read { .. } | BoardError::Unknown(_) => None,
        }
    }

    /// The 1-based line the error is about, if known.
    pub fn line(&self) -> Option<usize> {
        match self {
            BoardError::Parse { line, .. } | BoardError::Invalid { line, .. } => *line,
            BoardError::Named(e) => e.line,
            BoardError::Read { .. } | BoardError::Unknown(_) => None,
        }
    }
}

/// ", line 3, field `pitch`" (whatever is known).
fn at(line: Option<usize>, field: Option<&str>) -> String {
    let mut s = String::new();
    if let Some(l) = line {
        s += &format!(", line {l}");
    }
    if let Some(f) = field {
        s += &format!(", field `{f}`");
    }
    s
}

/// The built-in boards (each known by its `name`).
const BUILTIN: [fn() -> Board; 1] = [Board::hex600];

/// "hex600" (the names of the built-in boards).
fn builtin_names() -> String {
    BUILTIN.map(|make| make().name).join(", ")
}

impl Board {
    /// A built-in board by name (`hex600`).
    pub fn builtin(name: &str) -> Option<Board> {
        BUILTIN.iter().map(|make| make()).find(|b| b.name == name)
    }

    /// Read and validate a board file's text; errors name `<string>` as the origin.
    pub fn from_toml_str(text: &str) -> Result<Board, BoardError> {
        parse(text, "<string>")
    }

    /// The board as a board file's text ([`Board::from_toml_str`] reads it back equal).
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("a board serialises as TOML")
    }

    /// Read and validate a board file.
    pub fn load(path: impl AsRef<Path>) -> Result<Board, BoardError> {
        let path = path.as_ref();
        let text = crate::limits::read_text(path).map_err(|source| BoardError::Read {
            path: path.to_owned(),
            source,
        })?;
        parse(&text, &path.display().to_string())
    }

    /// The board a command line names: a built-in name (`hex600`), else a board file path.
    pub fn resolve(name_or_path: &str) -> Result<Board, BoardError> {
        if let Some(b) = Board::builtin(name_or_path) {
            return Ok(b);
        }
        let path = Path::new(name_or_path);
        if !path.exists() {
            return Err(BoardError::Unknown(name_or_path.to_owned()));
        }
        Board::load(path)
    }

    /// The board the value `value` at `field` (a JSON path) of the file `file` names: a
    /// built-in name, else a board file inside the folder that holds `file`
    /// ([`crate::paths::inside`]). Anything else is refused naming `file` and `field`; a
    /// board file that does not read is refused as [`Board::load`] refuses it.
    pub fn resolve_in(value: &str, file: &Path, field: &str) -> Result<Board, BoardError> {
        if let Some(b) = Board::builtin(value) {
            return Ok(b);
        }
        let named = |m: crate::Invalid| BoardError::Named(m.at(field).in_file(file));
        let folder = file.parent().unwrap_or(Path::new(""));
        let path = crate::paths::inside(folder, value).map_err(named)?;
        if !path.is_file() {
            return Err(named(crate::Invalid(format!(
                "{value:?} is neither a built-in board ({}) nor a board file in {}",
                builtin_names(),
                match folder.as_os_str().is_empty() {
                    true => "the current folder".into(),
                    false => folder.display().to_string(),
                }
            ))));
        }
        Board::load(path)
    }
}

fn parse(text: &str, origin: &str) -> Result<Board, BoardError> {
    // One parse keeps the spans: every key's for errors after deserialising, the root's to
    // recognise a missing top-level key (its error spans the root table: no line helps).
    let mut keys = crate::tomlspan::KeySpans::default();
    let board: Result<Board, toml_edit::de::Error> = toml_edit::ImDocument::parse(text.to_owned())
        .map_err(Into::into)
        .and_then(|doc| {
            keys = crate::tomlspan::KeySpans::of(doc.as_table());
            toml_edit::de::from_document(doc)
        });
    let board = board.map_err(|e| {
        let span = e.span().filter(|s| Some(s) != keys.root.as_ref());
        BoardError::Parse {
            origin: origin.to_owned(),
            line: span
                .as_ref()
                .map(|s| crate::tomlspan::line_of(text, s.start)),
            field: span.and_then(|s| keys.field_at(&s)),
            message: e.message().trim().replace('\n', ", "),
        }
    })?;
    board.validate().map_err(|invalid| BoardError::Invalid {
        origin: origin.to_owned(),
        line: keys.line_of(&invalid.field, text),
        invalid,
    })?;
    Ok(board)
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEX600: &str = include_str!("../../../../rigs/boards/hex600.toml");

    #[test]
    fn shipped_hex600_file_equals_builtin() {
        assert_eq!(Board::from_toml_str(HEX600).unwrap(), Board::hex600());
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../rigs/boards/hex600.toml");
        assert_eq!(Board::load(path).unwrap(), Board::hex600());
        assert_eq!(Board::resolve(path).unwrap(), Board::hex600());
        assert_eq!(Board::resolve("hex600").unwrap(), Board::hex600());
    }

    #[test]
    fn resolve_and_load_name_what_is_missing() {
        let e = Board::resolve("no/such/board.toml").unwrap_err();
        assert!(matches!(e, BoardError::Unknown(_)));
        assert!(e.to_string().contains("no/such/board.toml"), "{e}");
        let e = Board::load("no/such/board.toml").unwrap_err();
        assert!(matches!(e, BoardError::Read { .. }));
        assert!(e.to_string().contains("no/such/board.toml"), "{e}");
    }

    #[test]
    fn a_board_file_is_written_as_read() {
        let mut b = Board::hex600();
        b.name = "copy".into();
        b.pitch = 21.0;
        assert_eq!(Board::from_toml_str(&b.to_toml()).unwrap(), b);
    }

    #[test]
    fn a_named_board_stays_in_its_folder() {
        let dir = std::env::temp_dir().join(format!("hexcal-board-in-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("c.json");
        std::fs::write(dir.join("b.toml"), Board::hex600().to_toml()).unwrap();
        assert!(Board::resolve_in("hex600", &file, "board").is_ok());
        assert!(Board::resolve_in("b.toml", &file, "board").is_ok());
        for (bad, says) in [
            ("../b.toml", "is not a path inside"),
            ("/etc/passwd", "is not a path inside"),
            ("nothing.toml", "neither a built-in board"),
        ] {
            let e = Board::resolve_in(bad, &file, "board")
                .unwrap_err()
                .to_string();
            assert!(
                e.starts_with(&format!("{}: board: ", file.display())),
                "{e}"
            );
            assert!(e.contains(says), "{e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn measured_side_transform_is_read() {
        let text = format!(
            "{HEX600}\n[front_back]\nrotation = [0.01, 3.1, 0.0]\ntranslation = [0.5, 0.0, -10.2]\n"
        );
        let b = Board::from_toml_str(&text).unwrap();
        let t = b.front_back.unwrap();
        assert_eq!(t.rotation, [0.01, 3.1, 0.0]);
        assert_eq!(t.translation, [0.5, 0.0, -10.2]);
        assert_eq!(b.side_transform(super::super::Side::Back), t.isometry());
    }

    /// `HEX600` with the line starting `key =` replaced by `line`.
    fn with_line(key: &str, line: &str) -> String {
        let mut found = false;
        let out: Vec<&str> = HEX600
            .lines()
            .map(|l| {
                if l.starts_with(&format!("{key} =")) {
                    found = true;
                    line
                } else {
                    l
                }
            })
            .collect();
        assert!(found, "no line {key} = in hex600.toml");
        out.join("\n")
    }

    /// Line number of the line starting `key =` (or `[table]`) in `HEX600`.
    fn line_no(key: &str) -> usize {
        1 + HEX600
            .lines()
            .position(|l| l.starts_with(&format!("{key} =")) || l.starts_with(key))
            .unwrap()
    }

    #[test]
    fn parse_errors_name_field_and_line() {
        let e = Board::from_toml_str(&with_line("pitch", "pitch = \"twenty\"")).unwrap_err();
        assert!(matches!(e, BoardError::Parse { .. }), "{e}");
        assert_eq!(e.field(), Some("pitch"), "{e}");
        assert_eq!(e.line(), Some(line_no("pitch")), "{e}");

        let e =
            Board::from_toml_str(&with_line("front_side", "front_side = \"00101\"")).unwrap_err();
        assert_eq!(e.field(), Some("codes.front_side"), "{e}");
        assert_eq!(e.line(), Some(line_no("front_side")), "{e}");

        let e = Board::from_toml_str(&format!("pitchh = 20.0\n{HEX600}")).unwrap_err();
        assert_eq!((e.field(), e.line()), (Some("pitchh"), Some(1)), "{e}");
        assert!(e.to_string().contains("unknown field"), "{e}");
        // Appended at the end, a key belongs to the last table, [codes].
        let e =
            Board::from_toml_str(&format!("{HEX600}\nfront_centre = \"011111\"\n")).unwrap_err();
        assert_eq!(e.field(), Some("codes.front_centre"), "{e}");

        let e = Board::from_toml_str(&with_line("radius", "")).unwrap_err();
        assert_eq!(e.line(), None, "{e}");
        assert!(e.to_string().contains("missing field `radius`"), "{e}");
        // A code a double-sided board needs: named, at its table's line.
        let e = Board::from_toml_str(&with_line("back_side", "")).unwrap_err();
        assert_eq!(
            (e.field(), e.line()),
            (Some("codes.back_side"), Some(line_no("[codes]"))),
            "{e}"
        );
        assert!(
            e.to_string().contains("missing: a double-sided board"),
            "{e}"
        );
        let e = Board::from_toml_str(&with_line("thickness", "")).unwrap_err();
        assert_eq!((e.field(), e.line()), (Some("thickness"), None), "{e}");

        let e = Board::from_toml_str("pitch = 20.0\nradius = [\n").unwrap_err();
        assert_eq!(e.line(), Some(3), "{e}");
    }

    const FRONT: &str = include_str!("../../../../rigs/boards/hex600-front.toml");

    /// The shipped single-sided board: hex600's front, nothing on its back, no back code
    /// decodes.
    #[test]
    fn single_sided_board_file_has_no_back() {
        use super::super::{MarkerKind, Side, Sides};
        let b = Board::from_toml_str(FRONT).unwrap();
        let hex600 = Board::hex600();
        assert_eq!(b, hex600.front_only());
        assert_eq!((b.sides, b.name.as_str()), (Sides::One, "hex600-front"));
        assert_eq!(b.sides.list(), [Side::Front]);
        assert!(b.has(Side::Front) && !b.has(Side::Back));
        assert_eq!(b.circles(Side::Front), hex600.circles(Side::Front));
        assert_eq!(
            b.marker_cells(Side::Front),
            hex600.marker_cells(Side::Front)
        );
        assert!(b.circles(Side::Back).is_empty() && b.marker_cells(Side::Back).is_empty());
        assert!(b.ringed(Side::Back).is_empty());
        for kind in [MarkerKind::BackCenter, MarkerKind::BackSide] {
            let code = hex600.codes.get(kind).unwrap();
            assert_eq!(b.codes.get(kind), None);
            assert!((0..6).all(|k| b.codes.decode(code.rotated(k)).is_none()));
        }
        // Without side marks the centre cell is the only marker.
        let bare: String = FRONT
            .lines()
            .filter(|l| !l.starts_with("marker_spacing") && !l.starts_with("front_side"))
            .collect::<Vec<_>>()
            .join("\n");
        let b = Board::from_toml_str(&bare).unwrap();
        assert_eq!(b.codes.present().count(), 1);
        assert_eq!(
            b.marker_cells(Side::Front),
            hex600.marker_cells(Side::Front)[..1]
        );
    }

    /// A single-sided board refuses anything of a back, and side marks without their code or
    /// spacing, naming the field and its line.
    #[test]
    fn single_sided_board_refuses_a_back() {
        let line_of = |text: &str, start: &str| text.lines().position(|l| l.starts_with(start));
        for (extra, field) in [
            ("thickness = 10.0", "thickness"),
            (
                "[front_back]\nrotation = [0.0, 3.1, 0.0]\ntranslation = [0.0, 0.0, -10.0]",
                "front_back",
            ),
            ("back_center = \"000111\"", "codes.back_center"),
            ("back_side = \"001101\"", "codes.back_side"),
        ] {
            // Top-level keys go before [codes], the rest after it.
            let text = if extra.starts_with("thickness") {
                format!("{extra}\n{FRONT}")
            } else {
                format!("{FRONT}\n{extra}\n")
            };
            let e = Board::from_toml_str(&text).unwrap_err();
            assert_eq!(e.field(), Some(field), "{e}");
            let key = extra.split([' ', '\n']).next().unwrap();
            assert_eq!(e.line(), line_of(&text, key).map(|l| l + 1), "{e}");
            assert!(e.to_string().contains("has no back: remove it"), "{e}");
        }
        let no_spacing: String = FRONT
            .lines()
            .filter(|l| !l.starts_with("marker_spacing"))
            .collect::<Vec<_>>()
            .join("\n");
        let e = Board::from_toml_str(&no_spacing).unwrap_err();
        assert_eq!(e.field(), Some("marker_spacing"), "{e}");
        let no_code: String = FRONT
            .lines()
            .filter(|l| !l.starts_with("front_side"))
            .collect::<Vec<_>>()
            .join("\n");
        let e = Board::from_toml_str(&no_code).unwrap_err();
        assert_eq!(e.field(), Some("codes.front_side"), "{e}");
        let e = Board::from_toml_str(&FRONT.replace("sides = 1", "sides = 3")).unwrap_err();
        assert!(matches!(e, BoardError::Parse { .. }), "{e}");
        assert_eq!(
            (e.field(), e.line()),
            (Some("sides"), line_of(FRONT, "sides").map(|l| l + 1))
        );
        assert!(e.to_string().contains("1 or 2 printed sides"), "{e}");
    }

    #[test]
    fn invalid_errors_name_origin_field_and_line() {
        let e = Board::from_toml_str(&with_line("pitch", "pitch = 11.0")).unwrap_err();
        assert!(matches!(e, BoardError::Invalid { .. }), "{e}");
        assert_eq!(e.field(), Some("pitch"));
        assert_eq!(e.line(), Some(line_no("pitch")));
        let msg = e.to_string();
        assert!(msg.starts_with("board file <string>, line "), "{msg}");
        assert!(msg.contains("field `pitch`"), "{msg}");
    }
}
