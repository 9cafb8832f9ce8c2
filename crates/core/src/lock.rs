//! One writer per folder: a job that writes into a folder (a run's or a capture's dataset, a
//! calibration's outputs) first takes an exclusive lock on it, so a second job on the same
//! folder is refused instead of moving the first one's files about.
//!
//! The lock is the operating system's (`flock` on `FOLDER/hexcal.lock`): the kernel releases
//! it when the process ends in any way, so a crash or a kill never leaves a stale lock. The
//! file holds the holder's process id, read by a refused job to name it.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, Write};
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};

/// The lock file inside a locked folder.
pub const LOCK_FILE: &str = "hexcal.lock";

/// Why a folder could not be locked.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    /// Another process holds the folder.
    #[error(
        "{}: in use by another hexcal job (process {holder}): wait for it to end, or stop it, \
         or write to another folder",
        folder.display()
    )]
    Busy {
        /// The folder.
        folder: PathBuf,
        /// The holder's process id as it wrote it ("unknown" if unreadable).
        holder: String,
    },
    /// The folder or its lock file could not be created or locked.
    #[error("{}: cannot lock the folder: {source}", folder.display())]
    Io {
        /// The folder.
        folder: PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

/// An exclusive lock on a folder, held until dropped (or the process ends).
#[derive(Debug)]
pub struct FolderLock {
    /// The open lock file (the lock lives with this descriptor, released when it closes).
    _file: File,
    /// The folder.
    folder: PathBuf,
}

impl FolderLock {
    /// Create `folder` if needed and lock it; refused at once (no waiting) when another
    /// process, or another lock of this one, holds it.
    pub fn acquire(folder: &Path) -> Result<FolderLock, LockError> {
        let io = |source| LockError::Io {
            folder: folder.to_path_buf(),
            source,
        };
        std::fs::create_dir_all(folder).map_err(io)?;
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(folder.join(LOCK_FILE))
            .map_err(io)?;
        // SAFETY: flock on a descriptor this function owns; no memory is passed.
        let locked = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if locked != 0 {
            let e = std::io::Error::last_os_error();
            if e.kind() != std::io::ErrorKind::WouldBlock {
                return Err(io(e));
            }
            let mut holder = String::new();
            let _ = file.read_to_string(&mut holder);
            let holder = holder.trim();
            return Err(LockError::Busy {
                folder: folder.to_path_buf(),
                holder: if holder.is_empty() { "unknown" } else { holder }.to_string(),
            });
        }
        file.set_len(0).map_err(io)?;
        file.rewind().map_err(io)?;
        write!(file, "{}", std::process::id()).map_err(io)?;
        file.flush().map_err(io)?;
        Ok(FolderLock {
            _file: file,
            folder: folder.to_path_buf(),
        })
    }

    /// The locked folder.
    pub fn folder(&self) -> &Path {
        &self.folder
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_is_refused_naming_the_holder_until_the_first_is_dropped() {
        let dir = std::env::temp_dir().join(format!("hexcal-lock-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let first = FolderLock::acquire(&dir).unwrap();
        assert_eq!(first.folder(), dir);
        // flock locks belong to the open file: a second open in this process conflicts too.
        let e = FolderLock::acquire(&dir).unwrap_err();
        let pid = std::process::id().to_string();
        assert!(
            matches!(&e, LockError::Busy { holder, .. } if *holder == pid),
            "{e}"
        );
        assert!(e.to_string().contains(&format!("process {pid}")), "{e}");
        assert!(e.to_string().starts_with(&dir.display().to_string()), "{e}");
        drop(first);
        let again = FolderLock::acquire(&dir).unwrap();
        drop(again);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
