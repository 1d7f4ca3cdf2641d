//! The persistent job store: records in an embedded redb database, frames and results as
//! files beside it.
//!
//! ```text
//! DATA_DIR/
//!   jobs.redb              one record per job (JSON), committed durably
//!   jobs/<id>/input.exr    the uploaded frame (written as .part, fsynced, renamed)
//!   jobs/<id>/reference.exr
//!   jobs/<id>/result.json  the finished record, written just before result.exr
//!   jobs/<id>/result.exr   the denoised frame
//! ```
//!
//! Every file is written under a temporary name, flushed to disk and renamed
//! ([`crate::atomic`]), so a reader never sees half a file. A job's record is committed only after its input is on disk;
//! its result is served only after its record says `succeeded`. If the process dies
//! between writing `result.exr` and committing the record, recovery finds `result.json`
//! and `result.exr` and completes the record instead of running the job again.
//!
//! Locking: none of its own (redb serialises write transactions). The core calls it with
//! no state lock held; its record writes are ordered by the core's journal (see
//! [`crate::jobs`]).

use std::fs;
use std::path::{Path, PathBuf};

use redb::{Database, Durability, ReadableDatabase, ReadableTable, TableDefinition};

use super::record::JobRecord;
use crate::error::{Error, Result};

const JOBS: TableDefinition<&str, &[u8]> = TableDefinition::new("jobs");

pub struct Store {
    db: Database,
    root: PathBuf,
}

fn db_error(e: impl std::fmt::Display) -> Error {
    Error::Internal(format!("job database: {e}"))
}

impl Store {
    /// Opens (or creates) the store under `data_dir`. Fails if another daemon holds it.
    pub fn open(data_dir: &Path) -> Result<Store> {
        fs::create_dir_all(data_dir.join("jobs"))
            .map_err(|e| Error::internal(&format!("cannot create {}", data_dir.display()), e))?;
        let path = data_dir.join("jobs.redb");
        // A daemon that is still exiting may hold the file for a moment.
        let mut waited = 0;
        let db = loop {
            match Database::create(&path) {
                Ok(db) => break db,
                Err(redb::DatabaseError::DatabaseAlreadyOpen) if waited < 100 => {
                    if waited == 0 {
                        tracing::warn!("{} is in use; waiting for it", path.display());
                    }
                    waited += 1;
                    std::thread::sleep(std::time::Duration::from_millis(100));
                }
                Err(e) => return Err(Error::Internal(format!("cannot open {}: {e}", path.display()))),
            }
        };
        let txn = db.begin_write().map_err(db_error)?;
        txn.open_table(JOBS).map_err(db_error)?;
        txn.commit().map_err(db_error)?;
        Ok(Store { db, root: data_dir.to_path_buf() })
    }

    /// Writes a record durably (the call returns once it is on disk).
    pub fn put(&self, record: &JobRecord) -> Result<()> {
        let bytes = serde_json::to_vec(record).map_err(db_error)?;
        let mut txn = self.db.begin_write().map_err(db_error)?;
        txn.set_durability(Durability::Immediate).map_err(db_error)?;
        {
            let mut table = txn.open_table(JOBS).map_err(db_error)?;
            table.insert(record.id.as_str(), bytes.as_slice()).map_err(db_error)?;
        }
        txn.commit().map_err(db_error)
    }

    /// Removes the records of `ids` in one transaction.
    pub fn remove(&self, ids: &[&str]) -> Result<()> {
        let mut txn = self.db.begin_write().map_err(db_error)?;
        txn.set_durability(Durability::Immediate).map_err(db_error)?;
        {
            let mut table = txn.open_table(JOBS).map_err(db_error)?;
            for id in ids {
                table.remove(*id).map_err(db_error)?;
            }
        }
        txn.commit().map_err(db_error)
    }

    /// Every record, in no particular order. Records that cannot be decoded are logged and
    /// skipped (their files are kept for inspection).
    pub fn load_all(&self) -> Result<Vec<JobRecord>> {
        let txn = self.db.begin_read().map_err(db_error)?;
        let table = txn.open_table(JOBS).map_err(db_error)?;
        let mut out = Vec::new();
        for entry in table.iter().map_err(db_error)? {
            let (key, value) = entry.map_err(db_error)?;
            match serde_json::from_slice::<JobRecord>(value.value()) {
                Ok(r) => out.push(r),
                Err(e) => tracing::error!(job_id = key.value(), error = %e, "skipping an unreadable job record"),
            }
        }
        Ok(out)
    }

    pub fn jobs_dir(&self) -> PathBuf {
        self.root.join("jobs")
    }

    pub fn job_dir(&self, id: &str) -> PathBuf {
        self.jobs_dir().join(id)
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

    /// Deletes a job's directory; a missing directory is not an error.
    pub fn remove_files(&self, id: &str) {
        let dir = self.job_dir(id);
        if let Err(e) = fs::remove_dir_all(&dir) {
            if e.kind() != std::io::ErrorKind::NotFound {
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
