//! The persistent job store: records in an embedded redb database, and each job's
//! directory with its files and its own copy of its record.
//!
//! ```text
//! DATA_DIR/
//!   .lock                  held (flock) by the daemon that owns the directory
//!   jobs.redb              one record per job (JSON), committed durably: the index
//!   jobs/<id>/record.json  the same record, written before the database each time
//!   jobs/<id>/input.exr    the uploaded frame (written as .part, fsynced, renamed)
//!   jobs/<id>/reference.exr
//!   jobs/<id>/result.json  the finished record, written just before result.exr
//!   jobs/<id>/result.exr   the denoised frame
//!   jobs/<id>/preview-input.exr, preview-reference.exr
//!                          the colour of the uploaded frames (half float, R,G,B), kept
//!                          for the dashboard's previews once the uploads are removed
//!   quarantine/<id>.<ms>/  what recovery could not account for, kept for inspection
//!   jobs.redb.damaged-<ms> a database that could not be opened, kept for inspection
//! ```
//!
//! Every file is written under a temporary name, flushed to disk and renamed
//! ([`crate::atomic`]), so a reader never sees half a file. A job's record is committed only
//! after its input is on disk; its result is served only after its record says
//! `succeeded`. If the process dies between writing `result.exr` and committing the record,
//! recovery finds `result.json` and `result.exr` and completes the record instead of
//! running the job again.
//!
//! Each write of a record carries a revision number that grows with every write of this
//! store (across restarts: it starts above the largest one found). The directory's copy is
//! written first, then the database; recovery takes, per job, the copy with the larger
//! revision. So a database that is lost, emptied, damaged or rolled back to an earlier
//! commit is rebuilt from the directories, and nothing is deleted because the database
//! forgot it (docs/reliability.md, storage faults).
//!
//! After an I/O error redb refuses every later transaction until the database is opened
//! again; [`Store::put`] and [`Store::remove`] reopen it and retry once, so the store heals
//! as soon as the fault (a full disk, say) is gone.
//!
//! Locking: the database sits behind a `RwLock` that only a reopen takes for writing
//! (redb serialises write transactions itself). The core calls the store with no state
//! lock held; its record writes are ordered by the core's journal (see [`crate::jobs`]).

use std::fs;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{RwLock, RwLockReadGuard};

use redb::{Database, Durability, ReadableDatabase, ReadableTable, TableDefinition};

use super::record::JobRecord;
use crate::error::{Error, Result};

const JOBS: TableDefinition<&str, &[u8]> = TableDefinition::new("jobs");

/// The file a job's own copy of its record is kept in.
pub const RECORD_FILE: &str = "record.json";

pub struct Store {
    db: RwLock<Option<Database>>,
    db_path: PathBuf,
    root: PathBuf,
    /// The revision of the last record written.
    rev: AtomicU64,
}

/// A redb error, classified: I/O errors by their cause (a full disk is `storage_full`),
/// the rest as the database's own failures.
fn db_error(context: &str, e: impl Into<redb::Error>) -> Error {
    match e.into() {
        redb::Error::Io(io) => Error::storage(&format!("job database: {context}"), &io),
        redb::Error::PreviousIo => Error::Storage {
            full: false,
            message: format!("job database: {context}: an earlier I/O error left it unusable until it is reopened"),
        },
        other => Error::Internal(format!("job database: {context}: {other}")),
    }
}

/// Holds the data directory for this process (an exclusive `flock` on `DATA_DIR/.lock`),
/// released when dropped or when the process ends, however it ends.
pub struct DataDirLock {
    _file: fs::File,
}

impl DataDirLock {
    /// Takes the lock, waiting up to `wait` for a daemon that is still exiting; fails
    /// naming the directory when another process keeps it.
    pub fn acquire(data_dir: &Path, wait: std::time::Duration) -> Result<DataDirLock> {
        fs::create_dir_all(data_dir)
            .map_err(|e| Error::storage(&format!("cannot create {}", data_dir.display()), &e))?;
        let path = data_dir.join(".lock");
        let file = fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&path)
            .map_err(|e| Error::storage(&format!("cannot open {}", path.display()), &e))?;
        let started = std::time::Instant::now();
        let mut warned = false;
        loop {
            match file.try_lock() {
                Ok(()) => return Ok(DataDirLock { _file: file }),
                Err(fs::TryLockError::WouldBlock) if started.elapsed() < wait => {
                    if !warned {
                        tracing::warn!("{} is held by another process; waiting for it", path.display());
                        warned = true;
                    }
                    std::thread::sleep(std::time::Duration::from_millis(100));
                }
                Err(fs::TryLockError::WouldBlock) => {
                    return Err(Error::Unavailable(format!(
                        "the data directory {} is in use by another mcdenoise daemon (it holds {}); \
                         stop it or give this one another --data-dir",
                        data_dir.display(),
                        path.display()
                    )))
                }
                Err(fs::TryLockError::Error(e)) => {
                    return Err(Error::storage(&format!("cannot lock {}", path.display()), &e))
                }
            }
        }
    }
}

/// Opens or creates the database; a redb panic (some damaged files trip its assertions)
/// becomes an error.
fn open_db(path: &Path) -> std::result::Result<Database, String> {
    // A daemon that is still exiting may hold the file for a moment.
    for attempt in 0..100 {
        match std::panic::catch_unwind(|| Database::create(path)) {
            Ok(Ok(db)) => return Ok(db),
            Ok(Err(redb::DatabaseError::DatabaseAlreadyOpen)) if attempt < 99 => {
                std::thread::sleep(std::time::Duration::from_millis(100))
            }
            Ok(Err(e)) => return Err(e.to_string()),
            Err(panic) => return Err(format!("redb panicked: {}", crate::error::panic_message(panic.as_ref()))),
        }
    }
    Err("it is held by another process".into())
}

fn create_table(db: &Database) -> Result<()> {
    let txn = db.begin_write().map_err(|e| db_error("begin", e))?;
    txn.open_table(JOBS).map_err(|e| db_error("open the table", e))?;
    txn.commit().map_err(|e| db_error("commit", e))
}

impl Store {
    /// Opens (or creates) the store under `data_dir`. A database that cannot be opened
    /// (damaged, truncated) is moved aside as `jobs.redb.damaged-<ms>` and replaced by an
    /// empty one; recovery then rebuilds it from the job directories. Nothing is deleted.
    pub fn open(data_dir: &Path) -> Result<Store> {
        let jobs = data_dir.join("jobs");
        fs::create_dir_all(&jobs).map_err(|e| Error::storage(&format!("cannot create {}", jobs.display()), &e))?;
        let path = data_dir.join("jobs.redb");
        let db = match open_db(&path) {
            Ok(db) => db,
            Err(why) => {
                let aside = data_dir.join(format!("jobs.redb.damaged-{}", super::now_ms()));
                tracing::error!(
                    database = %path.display(),
                    kept_as = %aside.display(),
                    error = %why,
                    "the job database cannot be opened; it is kept aside and rebuilt from the job directories"
                );
                fs::rename(&path, &aside).map_err(|e| {
                    Error::storage(&format!("cannot move the damaged database {} aside", path.display()), &e)
                })?;
                open_db(&path).map_err(|e| Error::Internal(format!("cannot create {}: {e}", path.display())))?
            }
        };
        create_table(&db)?;
        Ok(Store { db: RwLock::new(Some(db)), db_path: path, root: data_dir.to_path_buf(), rev: 0.into() })
    }

    fn db(&self) -> Result<RwLockReadGuard<'_, Option<Database>>> {
        let guard = self.db.read().unwrap_or_else(std::sync::PoisonError::into_inner);
        if guard.is_none() {
            drop(guard);
            self.reopen()?;
            return Ok(self.db.read().unwrap_or_else(std::sync::PoisonError::into_inner));
        }
        Ok(guard)
    }

    /// Closes and opens the database again (redb needs it after an I/O error).
    pub fn reopen(&self) -> Result<()> {
        let mut slot = self.db.write().unwrap_or_else(std::sync::PoisonError::into_inner);
        // The old handle must be gone before the file can be opened again.
        *slot = None;
        let db = open_db(&self.db_path)
            .map_err(|e| Error::Storage { full: false, message: format!("cannot reopen the job database: {e}") })?;
        create_table(&db)?;
        *slot = Some(db);
        tracing::info!(database = %self.db_path.display(), "job database reopened");
        Ok(())
    }

    /// Runs a write transaction; after a storage failure the database is reopened and the
    /// transaction tried once more.
    fn write(&self, what: &str, f: impl Fn(&mut redb::Table<'_, &str, &[u8]>) -> Result<()>) -> Result<()> {
        let attempt = || -> Result<()> {
            let guard = self.db()?;
            let db = guard.as_ref().expect("opened by db()");
            let mut txn = db.begin_write().map_err(|e| db_error(what, e))?;
            txn.set_durability(Durability::Immediate).map_err(|e| db_error(what, e))?;
            {
                let mut table = txn.open_table(JOBS).map_err(|e| db_error(what, e))?;
                f(&mut table)?;
            }
            txn.commit().map_err(|e| db_error(what, e))
        };
        match attempt() {
            Err(Error::Storage { .. }) => {
                if let Err(e) = self.reopen() {
                    // Next call tries again.
                    *self.db.write().unwrap_or_else(std::sync::PoisonError::into_inner) = None;
                    return Err(e);
                }
                attempt()
            }
            other => other,
        }
    }

    /// Makes later revisions start above `rev` (recovery calls it with the largest found).
    pub fn note_revision(&self, rev: u64) {
        self.rev.fetch_max(rev, Ordering::SeqCst);
    }

    /// Writes a record durably: the job directory's copy, then the database (the call
    /// returns once both are on disk). Either failure is returned and classified.
    pub fn put(&self, record: &JobRecord) -> Result<()> {
        let mut record = record.clone();
        record.rev = self.rev.fetch_add(1, Ordering::SeqCst) + 1;
        let bytes = serde_json::to_vec(&record).map_err(|e| Error::internal("cannot encode a job record", e))?;
        let file = self.record_path(&record.id);
        crate::atomic::write(&file, &bytes)
            .map_err(|e| Error::storage(&format!("cannot write {}", file.display()), &e))?;
        self.write("write a record", |table| {
            table.insert(record.id.as_str(), bytes.as_slice()).map_err(|e| db_error("insert", e))?;
            Ok(())
        })
    }

    /// Removes the records of `ids`: each directory's copy first (so a crash cannot bring a
    /// removed job back from its directory), then the database entries in one transaction.
    pub fn remove(&self, ids: &[&str]) -> Result<()> {
        for id in ids {
            let file = self.record_path(id);
            match fs::remove_file(&file) {
                Ok(()) => {}
                Err(e) if e.kind() == io::ErrorKind::NotFound => {}
                Err(e) => return Err(Error::storage(&format!("cannot remove {}", file.display()), &e)),
            }
        }
        self.write("remove records", |table| {
            for id in ids {
                table.remove(*id).map_err(|e| db_error("remove", e))?;
            }
            Ok(())
        })
    }

    /// Every record in the database, in no particular order, and the entries that are not
    /// records.
    pub fn load_all(&self) -> Result<(Vec<JobRecord>, Vec<(String, Vec<u8>)>)> {
        let guard = self.db()?;
        let db = guard.as_ref().expect("opened by db()");
        let txn = db.begin_read().map_err(|e| db_error("read", e))?;
        let table = txn.open_table(JOBS).map_err(|e| db_error("read", e))?;
        let (mut records, mut unreadable) = (Vec::new(), Vec::new());
        for entry in table.iter().map_err(|e| db_error("read", e))? {
            let (key, value) = entry.map_err(|e| db_error("read", e))?;
            match serde_json::from_slice::<JobRecord>(value.value()) {
                Ok(r) => records.push(r),
                Err(e) => {
                    tracing::error!(job_id = key.value(), error = %e, "a job record in the database cannot be decoded");
                    unreadable.push((key.value().to_string(), value.value().to_vec()));
                }
            }
        }
        Ok((records, unreadable))
    }

    /// Deletes database entries that are not records (their bytes were kept by recovery).
    pub fn drop_entries(&self, keys: &[String]) -> Result<()> {
        self.write("drop unreadable entries", |table| {
            for k in keys {
                table.remove(k.as_str()).map_err(|e| db_error("remove", e))?;
            }
            Ok(())
        })
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn jobs_dir(&self) -> PathBuf {
        self.root.join("jobs")
    }

    pub fn quarantine_dir(&self) -> PathBuf {
        self.root.join("quarantine")
    }

    pub fn job_dir(&self, id: &str) -> PathBuf {
        self.jobs_dir().join(id)
    }

    pub fn record_path(&self, id: &str) -> PathBuf {
        self.job_dir(id).join(RECORD_FILE)
    }

    pub fn input_path(&self, id: &str) -> PathBuf {
        self.job_dir(id).join("input.exr")
    }

    pub fn reference_path(&self, id: &str) -> PathBuf {
        self.job_dir(id).join("reference.exr")
    }

    pub fn result_path(&self, id: &str) -> PathBuf {
        self.job_dir(id).join("result.exr")
    }

    pub fn summary_path(&self, id: &str) -> PathBuf {
        self.job_dir(id).join("result.json")
    }

    /// The kept colour of an upload (`which`: `input` or `reference`), for previews.
    pub fn preview_source_path(&self, id: &str, which: &str) -> PathBuf {
        self.job_dir(id).join(format!("preview-{which}.exr"))
    }

    /// Moves `dir` into the quarantine folder (as `<name>.<ms>`), where nothing removes
    /// it; returns where it went.
    pub fn quarantine(&self, dir: &Path) -> io::Result<PathBuf> {
        let q = self.quarantine_dir();
        fs::create_dir_all(&q)?;
        let name = dir.file_name().unwrap_or_default().to_string_lossy().to_string();
        let target = q.join(format!("{name}.{}", super::now_ms()));
        fs::rename(dir, &target)?;
        Ok(target)
    }

    /// Deletes a job's directory; a missing directory is not an error.
    pub fn remove_files(&self, id: &str) {
        let dir = self.job_dir(id);
        if let Err(e) = fs::remove_dir_all(&dir) {
            if e.kind() != io::ErrorKind::NotFound {
                tracing::warn!(job_id = id, error = %e, "cannot remove {}", dir.display());
            }
        }
    }

    /// Deletes the uploaded frames of a finished job (the result stays).
    pub fn remove_inputs(&self, id: &str) {
        for p in [self.input_path(id), self.reference_path(id)] {
            let _ = fs::remove_file(p);
        }
    }
}
