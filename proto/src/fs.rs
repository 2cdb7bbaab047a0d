//! Files: the one error every crate reports a failed file operation with, and the atomic write
//! for files other processes read while they change.

use std::io::Write;
use std::path::{Path, PathBuf};

/// A file or directory that cannot be created, read or written: which, and what was tried.
#[derive(Debug, thiserror::Error)]
#[error("{}: cannot {action}", path.display())]
pub struct FileError {
    pub path: PathBuf,
    pub action: &'static str,
    pub source: std::io::Error,
}

impl FileError {
    /// The error of `action` on `path`, for `map_err`.
    pub fn at(path: &Path, action: &'static str) -> impl FnOnce(std::io::Error) -> FileError {
        let path = path.to_path_buf();
        move |source| FileError {
            path,
            action,
            source,
        }
    }
}

/// Writes `bytes` to `path` through a temporary file in the same directory (tempfile's), synced
/// and renamed into place, so a reader sees the old content or the new, never a torn file. On
/// failure (a full disk) the temporary file is removed. The file gets the mode of any new file
/// (0666 less the umask), not a temporary file's 0600: configs, figures and Prometheus' targets
/// are for whoever shares the directory.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), FileError> {
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let write = || -> std::io::Result<()> {
        let mut builder = tempfile::Builder::new();
        // A new file's mode, which the kernel masks with the umask.
        #[cfg(unix)]
        builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
        let mut file = builder.tempfile_in(dir)?;
        file.write_all(bytes)?;
        file.as_file().sync_all()?;
        file.persist(path).map_err(|e| e.error)?;
        Ok(())
    };
    write().map_err(FileError::at(path, "write"))
}

#[cfg(all(test, unix))]
mod tests {
    use std::os::unix::fs::PermissionsExt;

    /// An atomically written file has the mode a plainly created one gets under the same umask.
    #[test]
    fn an_atomic_write_leaves_a_new_files_mode() {
        let dir = tempfile::tempdir().unwrap();
        let (atomic, plain) = (dir.path().join("atomic"), dir.path().join("plain"));
        super::write_atomic(&atomic, b"a").unwrap();
        std::fs::write(&plain, b"p").unwrap();
        let mode = |p: &std::path::Path| std::fs::metadata(p).unwrap().permissions().mode();
        assert_eq!(mode(&atomic), mode(&plain));
    }
}
