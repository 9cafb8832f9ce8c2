//! Names that become paths (docs/limits.md "Paths"): every name a file gives that hexcal
//! turns into a path to read or write is checked here, so that no file can make hexcal read
//! or write outside the folder it belongs to.
//!
//! Takes a name from a file (a scene's output `name`, a stack's frame `file`, a `board`
//! value of a dataset, correspondences or held-out file) and the folder it must stay in;
//! gives the path inside that folder, or an [`Invalid`] saying why the name cannot be one.
//! Two rules: a *plain file name* ([`file_name`]) has no folder part at all; a *path inside
//! a folder* ([`inside`]) is relative, has no `..`, and does not leave the folder through a
//! symbolic link ([`contained`]).

use crate::invalid::Invalid;
use std::path::{Component, Path, PathBuf};

/// The longest path inside a folder a file may name (bytes).
pub const MAX_PATH_BYTES: usize = 4096;

/// `Err` unless `name` is a plain file name: not empty, at most
/// [`MAX_NAME_BYTES`](crate::limits::MAX_NAME_BYTES), no `/`, `\`, control character, and
/// not `.` or `..`.
pub fn file_name(name: &str) -> Result<(), Invalid> {
    crate::limits::plain_name(
        name,
        "an empty name cannot name a file",
        "is not a plain file name",
    )
}

/// The path `relative` names inside `folder`: `Err` unless it is relative, not empty, at
/// most [`MAX_PATH_BYTES`], made of plain names only (no `..`, `.`, root or drive), and,
/// when it exists, inside `folder` after symbolic links are followed ([`contained`]).
pub fn inside(folder: &Path, relative: &str) -> Result<PathBuf, Invalid> {
    let plain = !relative.is_empty()
        && relative.len() <= MAX_PATH_BYTES
        && !relative.contains('\\')
        && !relative.chars().any(char::is_control)
        && Path::new(relative)
            .components()
            .all(|c| matches!(c, Component::Normal(_)));
    if !plain {
        return Err(Invalid(format!(
            "{relative:?} is not a path inside {} (relative, no .., at most \
             {MAX_PATH_BYTES} bytes)",
            folder_shown(folder)
        )));
    }
    let path = folder.join(relative);
    if path.symlink_metadata().is_ok() {
        contained(folder, &path)?;
    }
    Ok(path)
}

/// `Err` unless the existing `path` is inside `folder` once symbolic links are followed
/// (a link to a file elsewhere is refused, one to a file within the folder is not).
pub fn contained(folder: &Path, path: &Path) -> Result<(), Invalid> {
    let unresolvable = |e: std::io::Error| Invalid(format!("{}: {e}", path.display()));
    let real_folder = folder.canonicalize().map_err(unresolvable)?;
    let real = path.canonicalize().map_err(unresolvable)?;
    if !real.starts_with(&real_folder) {
        return Err(Invalid(format!(
            "{} leads out of {} (to {})",
            path.display(),
            folder_shown(folder),
            real.display()
        )));
    }
    Ok(())
}

/// A folder as a refusal shows it (`the current folder` for the empty path).
fn folder_shown(folder: &Path) -> String {
    match folder.as_os_str().is_empty() {
        true => "the current folder".into(),
        false => folder.display().to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_names_only() {
        for bad in ["", ".", "..", "../x", "a/b", "/etc/passwd", "a\\b", "a\nb"] {
            assert!(file_name(bad).is_err(), "{bad:?}");
        }
        assert!(file_name(&"x".repeat(101)).is_err());
        assert!(file_name("view 1.png").is_ok());
    }

    #[test]
    fn paths_stay_inside_their_folder() {
        let dir = std::env::temp_dir().join(format!("hexcal-paths-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        std::fs::write(dir.join("sub/board.toml"), "x").unwrap();
        assert_eq!(
            inside(&dir, "sub/board.toml").unwrap(),
            dir.join("sub/board.toml")
        );
        assert!(
            inside(&dir, "missing.toml").is_ok(),
            "existence is not checked"
        );
        for bad in [
            "",
            "../x.toml",
            "sub/../../x",
            "/etc/passwd",
            "./x",
            "a\\..\\b",
        ] {
            let e = inside(&dir, bad).unwrap_err();
            assert!(e.contains("is not a path inside"), "{bad:?}: {e}");
        }
        #[cfg(unix)]
        {
            let outside = dir.with_extension("outside");
            std::fs::write(&outside, "secret").unwrap();
            std::os::unix::fs::symlink(&outside, dir.join("link.toml")).unwrap();
            std::os::unix::fs::symlink("sub/board.toml", dir.join("near.toml")).unwrap();
            let e = inside(&dir, "link.toml").unwrap_err();
            assert!(e.contains("leads out of"), "{e}");
            assert!(inside(&dir, "near.toml").is_ok());
            std::fs::remove_file(outside).unwrap();
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
