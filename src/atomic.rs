//! Writing files so that no reader ever sees half of one: the bytes go to a temporary
//! name beside the target ([`part_path`]), are flushed to disk, and the file is renamed
//! into place, then the directory entry is flushed too. A file dropped before
//! [`File::commit`] removes its temporary.
//!
//! The one way the crate writes files: the job store's uploads, results and summaries,
//! the outputs of `mcdenoise run` and `mcdenoise preprocess`, and the client's downloads.
//! Temporary names carry the process id, so two processes writing the same target do not
//! write into each other's temporary; recovery removes any `*.part` a crash left behind.

use std::fs;
use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use tokio::io::AsyncWriteExt;

/// The temporary name `path` is written under: `<name>.<pid>.part`, beside it.
pub fn part_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".{}.part", std::process::id()));
    path.with_file_name(name)
}

/// Whether `path` is a temporary of this module (of any process).
pub fn is_part(path: &Path) -> bool {
    path.extension().is_some_and(|e| e == "part")
}

/// Flushes the directory entry of `path` (after a rename).
pub fn sync_dir(path: &Path) -> std::io::Result<()> {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => fs::File::open(dir)?.sync_all(),
        _ => Ok(()),
    }
}

/// Writes `bytes` to `path` atomically and durably.
pub fn write(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut file = File::create(path)?;
    file.write_all(bytes)?;
    file.commit()
}

/// A file being written atomically (blocking I/O).
pub struct File {
    file: Option<fs::File>,
    tmp: PathBuf,
    path: PathBuf,
}

impl File {
    pub fn create(path: &Path) -> std::io::Result<File> {
        let tmp = part_path(path);
        let file = fs::File::create(&tmp)?;
        Ok(File { file: Some(file), tmp, path: path.to_path_buf() })
    }

    fn inner(&mut self) -> &mut fs::File {
        self.file.as_mut().expect("open until committed")
    }

    /// Flushes the file to disk and moves it into place.
    pub fn commit(mut self) -> std::io::Result<()> {
        let file = self.file.take().expect("open until committed");
        file.sync_all()?;
        drop(file);
        fs::rename(&self.tmp, &self.path)?;
        sync_dir(&self.path)
    }
}

impl Write for File {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.inner().write(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner().flush()
    }
}

impl Seek for File {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.inner().seek(pos)
    }
}

impl Drop for File {
    fn drop(&mut self) {
        if self.file.take().is_some() {
            let _ = fs::remove_file(&self.tmp);
        }
    }
}

/// A file being written atomically (tokio I/O, buffered).
pub struct AsyncFile {
    file: Option<tokio::io::BufWriter<tokio::fs::File>>,
    tmp: PathBuf,
    path: PathBuf,
}

impl AsyncFile {
    pub async fn create(path: &Path) -> std::io::Result<AsyncFile> {
        let tmp = part_path(path);
        let file = tokio::fs::File::create(&tmp).await?;
        Ok(AsyncFile { file: Some(tokio::io::BufWriter::with_capacity(1 << 20, file)), tmp, path: path.to_path_buf() })
    }

    pub async fn write_all(&mut self, data: &[u8]) -> std::io::Result<()> {
        self.file.as_mut().expect("open until committed").write_all(data).await
    }

    /// Flushes the file to disk and moves it into place.
    pub async fn commit(mut self) -> std::io::Result<()> {
        let mut file = self.file.take().expect("open until committed");
        file.flush().await?;
        let file = file.into_inner();
        file.sync_all().await?;
        drop(file);
        tokio::fs::rename(&self.tmp, &self.path).await?;
        let path = self.path.clone();
        tokio::task::spawn_blocking(move || sync_dir(&path)).await.map_err(std::io::Error::other)?
    }
}

impl Drop for AsyncFile {
    fn drop(&mut self) {
        if self.file.take().is_some() {
            // Small and rare (a refused or interrupted write): removing inline is fine.
            let _ = fs::remove_file(&self.tmp);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_committed_file_replaces_the_target_and_a_dropped_one_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("out.exr");
        write(&target, b"first").unwrap();
        let mut f = File::create(&target).unwrap();
        f.write_all(b"second").unwrap();
        assert_eq!(fs::read(&target).unwrap(), b"first", "readers see the old file until the commit");
        f.commit().unwrap();
        assert_eq!(fs::read(&target).unwrap(), b"second");
        let mut f = File::create(&target).unwrap();
        f.write_all(b"half").unwrap();
        drop(f);
        assert_eq!(fs::read(&target).unwrap(), b"second");
        let names: Vec<_> = fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, ["out.exr"], "no temporary left");
        assert!(is_part(&part_path(&target)) && !is_part(&target));
    }

    #[tokio::test]
    async fn the_async_file_commits_the_same_way() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("result.exr");
        let mut f = AsyncFile::create(&target).await.unwrap();
        f.write_all(b"abc").await.unwrap();
        assert!(!target.exists());
        f.commit().await.unwrap();
        assert_eq!(fs::read(&target).unwrap(), b"abc");
        let mut f = AsyncFile::create(&dir.path().join("other.exr")).await.unwrap();
        f.write_all(b"x").await.unwrap();
        drop(f);
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
