//! The library's module graph follows its layers (docs/design.md §1b): every `crate::X`
//! path in non-test code of a top-level module names a module in a lower layer, or an
//! earlier module of the same layer. So the graph has no cycle, and a stage never reaches
//! back up. Test code (files named `tests.rs`, folders `tests/`, and everything after a
//! `#[cfg(test)]` line) may use any module.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The layers, bottom first; within a layer, the order data flows.
const LAYERS: &[&[&str]] = &[
    &["atomic", "tomlspan", "limits"],
    &["board", "camera", "pattern", "images", "dataset"],
    &["sim"],
    &[
        "rig",
        "capture",
        "phase",
        "detect",
        "grid",
        "correspond",
        "calib",
        "report",
    ],
    &["app", "bench"],
];

/// Rank of a module: (layer, position in the layer).
fn rank(module: &str) -> Option<(usize, usize)> {
    LAYERS
        .iter()
        .enumerate()
        .find_map(|(l, mods)| mods.iter().position(|m| *m == module).map(|p| (l, p)))
}

/// Every `.rs` file under `dir`, recursively.
fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The non-test code of a file, without comments.
fn code(text: &str) -> String {
    let text = text.split("#[cfg(test)]").next().unwrap_or("");
    text.lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The top-level modules named by `crate::X` paths in `code`.
fn uses(code: &str) -> Vec<String> {
    code.match_indices("crate::")
        .filter(|(i, _)| {
            // Not part of a longer identifier (e.g. `hexcal_crate::`).
            code[..*i]
                .chars()
                .last()
                .is_none_or(|c| !(c.is_alphanumeric() || c == '_'))
        })
        .map(|(i, m)| {
            code[i + m.len()..]
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect()
        })
        .filter(|m: &String| !m.is_empty())
        .collect()
}

/// Each top-level module's `crate::` dependencies, from its non-test files.
fn graph() -> BTreeMap<String, BTreeMap<String, PathBuf>> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut edges: BTreeMap<String, BTreeMap<String, PathBuf>> = BTreeMap::new();
    for file in files {
        let rel = file.strip_prefix(&src).unwrap();
        let parts: Vec<String> = rel
            .iter()
            .map(|p| p.to_string_lossy().trim_end_matches(".rs").to_string())
            .collect();
        let test_file = parts.last().is_some_and(|p| p == "tests")
            || parts[..parts.len() - 1].iter().any(|p| p == "tests");
        let module = parts[0].clone();
        if test_file || ["lib", "main", "cli", "benchcmd"].contains(&module.as_str()) {
            continue;
        }
        let text = std::fs::read_to_string(&file).unwrap();
        for used in uses(&code(&text)) {
            if used != module {
                edges
                    .entry(module.clone())
                    .or_default()
                    .entry(used)
                    .or_insert_with(|| rel.to_owned());
            }
        }
    }
    edges
}

#[test]
fn every_module_uses_only_lower_or_earlier_modules() {
    let mut wrong = Vec::new();
    for (module, used) in graph() {
        let Some(me) = rank(&module) else {
            wrong.push(format!("{module}: not in the layer table"));
            continue;
        };
        for (other, file) in used {
            match rank(&other) {
                Some(r) if r < me => {}
                Some(_) => wrong.push(format!(
                    "{module} uses {other} ({}): a later or higher module",
                    file.display()
                )),
                None => wrong.push(format!(
                    "{other} (used by {module}): not in the layer table"
                )),
            }
        }
    }
    assert!(wrong.is_empty(), "layer violations:\n{}", wrong.join("\n"));
}

#[test]
fn the_layer_table_names_every_top_level_module() {
    let lib =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("src/lib.rs")).unwrap();
    let declared: Vec<&str> = lib
        .lines()
        .filter_map(|l| {
            let l = l
                .trim_start_matches("pub(crate) ")
                .trim_start_matches("pub ");
            l.strip_prefix("mod ")?.strip_suffix(';')
        })
        .collect();
    assert!(declared.len() > 10, "modules of lib.rs: {declared:?}");
    for m in declared {
        assert!(
            rank(m).is_some(),
            "src/lib.rs declares {m}, missing from LAYERS"
        );
    }
}

#[test]
fn the_check_sees_a_violation() {
    // The parser itself: a path into a higher module is found, a comment is not.
    let found = uses(&code(
        "use crate::calib::solve;\n// crate::report\nfn f() { crate::app::run(); }",
    ));
    assert_eq!(found, ["calib", "app"]);
    assert!(rank("calib") > rank("rig") && rank("app") > rank("report"));
}
