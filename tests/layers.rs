//! The layers are crates (docs/design.md §1b), so Cargo itself keeps a stage from reaching
//! up. This test checks what Cargo cannot see:
//! - the crate graph: which hexcal crate may depend on which (from `cargo metadata`), and that
//!   the vocabulary and calibration crates pull in no device driver, serial port or server;
//! - inside each crate, its top-level modules in data order: a module uses only itself and
//!   earlier modules, item by item (the source is parsed; items under `#[cfg(test)]` and
//!   `#[test]` functions are test code and may use anything), and every source file is
//!   reached from the crate root, so no production line goes unchecked;
//! - the binary: it parses arguments, calls `hexcal::app` (or the `hexcal::bench` harnesses)
//!   and prints.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use syn::visit::Visit;

/// Each hexcal crate and the hexcal crates it may depend on (normal dependencies).
const CRATES: &[(&str, &[&str])] = &[
    ("hexcal-firmware-protocol", &[]),
    ("hexcal-simulator", &["hexcal-firmware-protocol"]),
    ("hexcal-core", &[]),
    ("hexcal-sim", &["hexcal-core", "hexcal-simulator"]),
    (
        "hexcal-rig",
        &[
            "hexcal-core",
            "hexcal-sim",
            "hexcal-simulator",
            "hexcal-firmware-protocol",
        ],
    ),
    // The simulated world only for the decoder's accuracy harness (feature `bench`).
    ("hexcal-vision", &["hexcal-core", "hexcal-sim"]),
    ("hexcal-calib", &["hexcal-core"]),
    (
        "hexcal",
        &[
            "hexcal-core",
            "hexcal-sim",
            "hexcal-rig",
            "hexcal-vision",
            "hexcal-calib",
            "hexcal-simulator",
        ],
    ),
    // The Python package: the camera model, calibration files, image stages, no driver.
    (
        "hexcal-py",
        &["hexcal-core", "hexcal-vision", "hexcal-calib"],
    ),
    (
        "hexcal-fuzz",
        &["hexcal", "hexcal-firmware-protocol", "hexcal-simulator"],
    ),
];

/// Crates a user of the camera model and the calibration files must not have to build.
const HEAVY: &[&str] = &[
    "aravis",
    "aravis-sys",
    "v4l",
    "winit",
    "softbuffer",
    "x11-dl",
    "serialport",
    "tiny_http",
    "crossbeam-channel",
    "signal-hook",
    "clap",
];

/// `cargo metadata` of the workspace, resolved.
fn metadata() -> serde_json::Value {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = std::process::Command::new(cargo)
        .args(["metadata", "--format-version", "1"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("cargo metadata runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("cargo metadata gives JSON")
}

/// The workspace's packages by name.
fn members(meta: &serde_json::Value) -> BTreeMap<String, &serde_json::Value> {
    let ids: BTreeSet<&str> = meta["workspace_members"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    meta["packages"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| ids.contains(p["id"].as_str().unwrap()))
        .map(|p| (p["name"].as_str().unwrap().to_string(), p))
        .collect()
}

/// A package's dependencies of one kind (`None`: normal) by name.
fn dependencies<'a>(package: &'a serde_json::Value, kind: Option<&str>) -> Vec<&'a str> {
    package["dependencies"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|d| d["kind"].as_str() == kind)
        .map(|d| d["name"].as_str().unwrap())
        .collect()
}

#[test]
fn every_crate_depends_only_on_the_layers_below_it() {
    let meta = metadata();
    let members = members(&meta);
    let allowed: BTreeMap<&str, &[&str]> = CRATES.iter().copied().collect();
    for (name, package) in &members {
        let Some(allowed) = allowed.get(name.as_str()) else {
            panic!("{name} is a workspace crate this test does not place in a layer");
        };
        for dep in dependencies(package, None) {
            assert!(
                !members.contains_key(dep) || allowed.contains(&dep),
                "{name} depends on {dep}: not a layer below it"
            );
        }
        // Tests may use crates of the same layer or below, never the application.
        for dep in dependencies(package, Some("dev")) {
            assert!(
                dep != "hexcal" || name == "hexcal",
                "{name}'s tests depend on the application crate"
            );
        }
    }
    for dep in ["aravis", "v4l", "winit", "softbuffer"] {
        let users: Vec<&str> = members
            .iter()
            .filter(|(_, p)| dependencies(p, None).contains(&dep))
            .map(|(n, _)| n.as_str())
            .collect();
        assert_eq!(
            users,
            ["hexcal-rig"],
            "{dep} is a driver of the rig crate only"
        );
    }
}

#[test]
fn the_vocabulary_and_calibration_crates_build_no_driver_or_server() {
    let meta = metadata();
    let nodes: BTreeMap<&str, &serde_json::Value> = meta["resolve"]["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| (n["id"].as_str().unwrap(), n))
        .collect();
    let name_of = |id: &str| {
        meta["packages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["id"] == id)
            .map(|p| p["name"].as_str().unwrap().to_string())
            .unwrap()
    };
    for root in ["hexcal-core", "hexcal-calib"] {
        let start = nodes
            .keys()
            .find(|id| name_of(id) == root)
            .copied()
            .unwrap();
        // Every crate a build of `root` compiles: normal and build dependencies, transitively.
        let (mut seen, mut todo) = (BTreeSet::from([start]), vec![start]);
        while let Some(id) = todo.pop() {
            for dep in nodes[id]["deps"].as_array().unwrap() {
                let normal = dep["dep_kinds"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|k| k["kind"].as_str() != Some("dev"));
                let dep = dep["pkg"].as_str().unwrap();
                if normal && seen.insert(dep) {
                    todo.push(dep);
                }
            }
        }
        let names: BTreeSet<String> = seen.iter().map(|id| name_of(id)).collect();
        for heavy in HEAVY {
            assert!(!names.contains(*heavy), "{root} builds {heavy}");
        }
        let hexcal: Vec<&String> = names.iter().filter(|n| n.starts_with("hexcal")).collect();
        let want: Vec<&str> = match root {
            "hexcal-core" => vec!["hexcal-core"],
            _ => vec!["hexcal-calib", "hexcal-core"],
        };
        assert_eq!(hexcal, want, "{root} builds these hexcal crates");
    }
}

/// Whether attributes mark test code: `#[test]`, `#[cfg(test)]` or `#[cfg(all(test, …))]`
/// (`#[cfg(any(test, feature = …))]` is production code behind a feature).
fn is_test(attrs: &[syn::Attribute]) -> bool {
    attrs.iter().any(|a| {
        if a.path().is_ident("test") {
            return true;
        }
        if !a.path().is_ident("cfg") {
            return false;
        }
        let tokens = a
            .meta
            .require_list()
            .map(|l| l.tokens.to_string())
            .unwrap_or_default();
        tokens == "test" || (tokens.starts_with("all") && tokens.contains("test"))
    })
}

/// The `crate::M` modules named in a file's production items.
#[derive(Default)]
struct Uses {
    /// Module name → the first file naming it.
    modules: BTreeMap<String, PathBuf>,
    /// The file being read.
    file: PathBuf,
}

impl Uses {
    fn note(&mut self, module: String) {
        self.modules
            .entry(module)
            .or_insert_with(|| self.file.clone());
    }
}

impl<'a> Visit<'a> for Uses {
    fn visit_item(&mut self, i: &'a syn::Item) {
        let attrs = match i {
            syn::Item::Const(x) => &x.attrs,
            syn::Item::Enum(x) => &x.attrs,
            syn::Item::Fn(x) => &x.attrs,
            syn::Item::Impl(x) => &x.attrs,
            syn::Item::Mod(x) => &x.attrs,
            syn::Item::Static(x) => &x.attrs,
            syn::Item::Struct(x) => &x.attrs,
            syn::Item::Trait(x) => &x.attrs,
            syn::Item::Type(x) => &x.attrs,
            syn::Item::Use(x) => &x.attrs,
            syn::Item::Macro(x) => &x.attrs,
            _ => return syn::visit::visit_item(self, i),
        };
        if !is_test(attrs) {
            syn::visit::visit_item(self, i);
        }
    }

    fn visit_impl_item_fn(&mut self, f: &'a syn::ImplItemFn) {
        if !is_test(&f.attrs) {
            syn::visit::visit_impl_item_fn(self, f);
        }
    }

    fn visit_path(&mut self, p: &'a syn::Path) {
        let mut s = p.segments.iter();
        if let (Some(first), Some(second)) = (s.next(), s.next()) {
            if first.ident == "crate" {
                self.note(second.ident.to_string());
            }
        }
        syn::visit::visit_path(self, p);
    }

    fn visit_use_tree(&mut self, t: &'a syn::UseTree) {
        if let syn::UseTree::Path(p) = t {
            if p.ident == "crate" {
                let mut inner = vec![&*p.tree];
                while let Some(t) = inner.pop() {
                    match t {
                        syn::UseTree::Path(q) => self.note(q.ident.to_string()),
                        syn::UseTree::Name(n) => self.note(n.ident.to_string()),
                        syn::UseTree::Rename(r) => self.note(r.ident.to_string()),
                        syn::UseTree::Group(g) => inner.extend(g.items.iter()),
                        syn::UseTree::Glob(_) => {}
                    }
                }
                return;
            }
        }
        syn::visit::visit_use_tree(self, t);
    }

    fn visit_macro(&mut self, m: &'a syn::Macro) {
        // Paths inside macro arguments (`format!("{}", crate::x::f())`) are tokens only.
        let tokens: Vec<String> = m.tokens.clone().into_iter().flat_map(flatten).collect();
        for w in tokens.windows(4) {
            if w[0] == "crate" && w[1] == ":" && w[2] == ":" {
                self.note(w[3].clone());
            }
        }
        syn::visit::visit_macro(self, m);
    }
}

/// A token tree as its tokens' texts, groups opened.
fn flatten(t: proc_macro2::TokenTree) -> Vec<String> {
    match t {
        proc_macro2::TokenTree::Group(g) => g.stream().into_iter().flat_map(flatten).collect(),
        other => vec![other.to_string()],
    }
}

/// The file of `mod name;` declared in `file`.
fn module_file(file: &Path, name: &str) -> PathBuf {
    let stem = file.file_stem().unwrap();
    let dir = if stem == "lib" || stem == "mod" || stem == "main" {
        file.parent().unwrap().to_path_buf()
    } else {
        file.with_extension("")
    };
    let flat = dir.join(format!("{name}.rs"));
    if flat.exists() {
        flat
    } else {
        dir.join(name).join("mod.rs")
    }
}

/// Reads `file` and the files of the modules it declares: the production `crate::` uses go to
/// `uses`, every file reached (test modules too) to `reached`.
fn walk(file: &Path, test: bool, uses: &mut Uses, reached: &mut BTreeSet<PathBuf>) {
    let text = std::fs::read_to_string(file).unwrap();
    let ast = syn::parse_file(&text).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    reached.insert(file.to_path_buf());
    if !test {
        uses.file = file.to_path_buf();
        uses.visit_file(&ast);
    }
    for item in &ast.items {
        if let syn::Item::Mod(m) = item {
            if m.content.is_none() {
                let child = module_file(file, &m.ident.to_string());
                walk(&child, test || is_test(&m.attrs), uses, reached);
            }
        }
    }
}

/// Every `.rs` file under `dir`, recursively.
fn rust_files(dir: &Path, out: &mut BTreeSet<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.insert(path);
        }
    }
}

/// Each crate's folder and its top-level modules in data order.
const MODULES: &[(&str, &[&str])] = &[
    (
        "crates/core",
        &[
            "atomic",
            "stop",
            "lock",
            "tomlspan",
            "invalid",
            "limits",
            "paths",
            "board",
            "camera",
            "pattern",
            "images",
            "dataset",
            "observations",
        ],
    ),
    (
        "crates/vision",
        &["stats", "phase", "detect", "grid", "correspond"],
    ),
    ("crates/rig", &["rig", "capture", "check"]),
    ("crates/calib", &["calib", "report"]),
    (
        "crates/py",
        &[
            "error",
            "arrays",
            "calibration",
            "triangulate",
            "vision",
            "calibrate",
        ],
    ),
    (".", &["app", "bench"]),
];

#[test]
fn modules_use_only_earlier_modules_of_their_crate_and_every_file_is_checked() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for (dir, order) in MODULES {
        let src = root.join(dir).join("src");
        let mut reached = BTreeSet::new();
        let lib = src.join("lib.rs");
        let ast = syn::parse_file(&std::fs::read_to_string(&lib).unwrap()).unwrap();
        for item in &ast.items {
            let syn::Item::Mod(m) = item else { continue };
            let name = m.ident.to_string();
            let mut uses = Uses::default();
            if m.content.is_none() {
                let test = is_test(&m.attrs);
                walk(&module_file(&lib, &name), test, &mut uses, &mut reached);
            }
            if is_test(&m.attrs) {
                continue;
            }
            let rank = |n: &str| order.iter().position(|o| *o == n);
            let mine = rank(&name).unwrap_or_else(|| panic!("{dir}: module {name} has no place"));
            for (used, file) in &uses.modules {
                if let Some(r) = rank(used) {
                    assert!(
                        r <= mine,
                        "{}: {name} uses crate::{used}, a later module",
                        file.display()
                    );
                }
            }
        }
        reached.insert(lib);
        if *dir == "." {
            reached.insert(src.join("main.rs"));
            let mut bin = Uses::default();
            walk(&src.join("main.rs"), false, &mut bin, &mut reached);
        }
        let mut all = BTreeSet::new();
        rust_files(&src, &mut all);
        let unreached: Vec<_> = all.difference(&reached).collect();
        assert!(
            unreached.is_empty(),
            "not reached from {dir}'s root: {unreached:?}"
        );
    }
}

/// The `hexcal::M` modules the binary names.
fn binary_uses() -> BTreeMap<String, PathBuf> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let (mut files, mut reached) = (Uses::default(), BTreeSet::new());
    walk(&src.join("main.rs"), false, &mut files, &mut reached);
    let mut out = BTreeMap::new();
    for file in reached {
        let text = std::fs::read_to_string(&file).unwrap();
        for (i, _) in text.match_indices("hexcal::") {
            let rest: String = text[i + 8..]
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            out.entry(rest).or_insert_with(|| file.clone());
        }
    }
    out
}

#[test]
fn the_binary_calls_only_the_application() {
    for (module, file) in binary_uses() {
        assert!(
            module == "app" || module == "bench",
            "{}: the binary reaches past the application into hexcal::{module}",
            file.display()
        );
    }
}
