//! Atomic file writes: a temporary file beside the target, then a rename, so that a reader
//! (or a crash) sees either the old content or the whole new one, never a part.

use std::path::{Path, PathBuf};

/// The temporary name used for `path`: `.NAME.tmpPID` in the same directory.
pub fn temp_path(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp{}", std::process::id()))
}

/// Let `write` fill a temporary file, then rename it to `path`; on any failure the
/// temporary file is removed and `path` is untouched. `io_error` turns a rename failure
/// into the caller's error type.
fn write_with<E>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
    io_error: impl FnOnce(std::io::Error) -> E,
) -> Result<(), E> {
    let tmp = temp_path(path);
    let result = write(&tmp).and_then(|()| std::fs::rename(&tmp, path).map_err(io_error));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Write `bytes` to `path` atomically.
pub fn write(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_with(path, |tmp| std::fs::write(tmp, bytes), |e| e)
}

/// Let `encode` fill a buffer in memory, then write it to `path` atomically. Every write
/// error reaches the caller: an encoder on a buffered file (as `image`'s `save` uses)
/// finishes it on drop, where a full disk's error is lost and a truncated file looks
/// written.
pub fn write_encoded<E>(
    path: &Path,
    encode: impl FnOnce(&mut std::io::Cursor<Vec<u8>>) -> Result<(), E>,
    io_error: impl FnOnce(std::io::Error) -> E,
) -> Result<(), E> {
    let mut bytes = std::io::Cursor::new(Vec::new());
    encode(&mut bytes)?;
    write(path, bytes.get_ref()).map_err(io_error)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failed_write_leaves_the_old_file_and_no_temporary() {
        let dir = std::env::temp_dir().join(format!("hexcal-atomic-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("out.txt");
        write(&path, b"old").unwrap();
        let r: Result<(), String> = write_with(
            &path,
            |tmp| {
                std::fs::write(tmp, b"partial").unwrap();
                Err("disk full".into())
            },
            |e| e.to_string(),
        );
        assert!(r.is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"old");
        assert!(!temp_path(&path).exists());
        write(&path, b"new").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn encoded_writes_whole_or_nothing() {
        use std::io::Write;
        let dir = std::env::temp_dir().join(format!("hexcal-encoded-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("out.bin");
        let r: Result<(), String> = write_encoded(
            &path,
            |out| {
                out.write_all(b"half").unwrap();
                Err("encoder failed".into())
            },
            |e| e.to_string(),
        );
        assert_eq!(r, Err("encoder failed".into()));
        assert!(!path.exists() && !temp_path(&path).exists());
        write_encoded(&path, |out| out.write_all(b"whole"), |e| e).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"whole");
        // A directory that does not exist: the write error reaches the caller.
        let gone = dir.join("missing").join("out.bin");
        assert!(write_encoded(&gone, |out| out.write_all(b"x"), |e| e).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
