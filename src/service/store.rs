//! The embedded store (redb, one file `pregrasp.redb` in the data folder).
//!
//! redb commits are atomic and crash-safe (copy-on-write B-trees, checksummed commits): a
//! crash in the middle of a write leaves the previous committed state. Every table maps a
//! string key to bytes (JSON for records, PLY for meshes).

use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::path::Path;

/// The tables of the store.
#[derive(Debug, Clone, Copy)]
pub enum Table {
    Cameras,
    Objects,
    Meshes,
    Grippers,
    Tracks,
    /// The tracker's compact snapshot (one record, key [`TRACKER_KEY`]).
    TrackerState,
    /// What is known about the scene (the support plane, key [`SUPPORT_PLANE_KEY`]).
    Scene,
}

/// Key of the support plane in [`Table::Scene`].
pub const SUPPORT_PLANE_KEY: &str = "support_plane";

/// Key of the tracker's snapshot in [`Table::TrackerState`].
pub const TRACKER_KEY: &str = "tracker";

impl Table {
    const ALL: [Table; 7] = [
        Table::Cameras,
        Table::Objects,
        Table::Meshes,
        Table::Grippers,
        Table::Tracks,
        Table::TrackerState,
        Table::Scene,
    ];

    fn def(self) -> TableDefinition<'static, &'static str, &'static [u8]> {
        TableDefinition::new(match self {
            Table::Cameras => "cameras",
            Table::Objects => "objects",
            Table::Meshes => "meshes",
            Table::Grippers => "grippers",
            Table::Tracks => "tracks",
            Table::TrackerState => "tracker_state",
            Table::Scene => "scene",
        })
    }
}

/// redb's page cache (its default is 1 GiB, which a long run fills with the pages of
/// snapshots rewritten every few seconds); the store's working set is a few megabytes.
pub const CACHE_BYTES: usize = 64 * 1024 * 1024;

/// A handle to the store; cheap to share behind an `Arc`.
pub struct Store {
    db: Database,
}

impl Store {
    /// Opens (or creates) `pregrasp.redb` in `data_dir`.
    pub fn open(data_dir: &Path) -> Result<Self, redb::Error> {
        std::fs::create_dir_all(data_dir).map_err(redb::Error::Io)?;
        let db = Database::builder()
            .set_cache_size(CACHE_BYTES)
            .create(data_dir.join("pregrasp.redb"))?;
        let txn = db.begin_write()?;
        for t in Table::ALL {
            txn.open_table(t.def())?;
        }
        txn.commit()?;
        Ok(Self { db })
    }

    pub fn put_bytes(&self, table: Table, key: &str, value: &[u8]) -> Result<(), redb::Error> {
        let txn = self.db.begin_write()?;
        {
            let mut t = txn.open_table(table.def())?;
            t.insert(key, value)?;
        }
        txn.commit()?;
        Ok(())
    }

    pub fn put<T: Serialize>(&self, table: Table, key: &str, value: &T) -> Result<(), redb::Error> {
        let bytes = serde_json::to_vec(value).map_err(|e| redb::Error::Io(std::io::Error::other(e)))?;
        self.put_bytes(table, key, &bytes)
    }

    /// Writes several records in one atomic transaction.
    pub fn put_many(&self, table: Table, records: &[(String, Vec<u8>)]) -> Result<(), redb::Error> {
        let txn = self.db.begin_write()?;
        {
            let mut t = txn.open_table(table.def())?;
            for (k, v) in records {
                t.insert(k.as_str(), v.as_slice())?;
            }
        }
        txn.commit()?;
        Ok(())
    }

    pub fn get_bytes(&self, table: Table, key: &str) -> Result<Option<Vec<u8>>, redb::Error> {
        let txn = self.db.begin_read()?;
        let t = txn.open_table(table.def())?;
        Ok(t.get(key)?.map(|v| v.value().to_vec()))
    }

    pub fn delete(&self, table: Table, key: &str) -> Result<bool, redb::Error> {
        let txn = self.db.begin_write()?;
        let existed = {
            let mut t = txn.open_table(table.def())?;
            t.remove(key)?.is_some()
        };
        txn.commit()?;
        Ok(existed)
    }

    /// Every record of a table that parses as `T` (records that do not are logged and skipped).
    pub fn list<T: DeserializeOwned>(&self, table: Table) -> Result<Vec<(String, T)>, redb::Error> {
        let txn = self.db.begin_read()?;
        let t = txn.open_table(table.def())?;
        let mut out = Vec::new();
        for row in t.iter()? {
            let (k, v) = row?;
            match serde_json::from_slice(v.value()) {
                Ok(val) => out.push((k.value().to_string(), val)),
                Err(e) => tracing::warn!("store: skipping unreadable record {} ({e})", k.value()),
            }
        }
        Ok(out)
    }
}

/// Serde of a [`crate::geometry::Pose`] in stored records as `{rotation_xyzw, translation_m}`
/// (the JSON of earlier versions, and the one people read).
pub mod pose_xyzw {
    use crate::geometry::{Pose, PoseXyzw};
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(p: &Pose, s: S) -> Result<S::Ok, S::Error> {
        PoseXyzw::from_pose(p).serialize(s)
    }
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Pose, D::Error> {
        PoseXyzw::deserialize(d)?.to_pose().map_err(serde::de::Error::custom)
    }
}

/// A field that is `None` when its stored JSON no longer parses (a record written by an
/// earlier version keeps the rest of its fields).
pub fn lenient<'de, D: serde::Deserializer<'de>, T: DeserializeOwned>(d: D) -> Result<Option<T>, D::Error> {
    let v = <serde_json::Value as serde::Deserialize>::deserialize(d)?;
    Ok(serde_json::from_value(v).ok())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_survive_reopening() {
        let dir = tempfile::tempdir().unwrap();
        {
            let s = Store::open(dir.path()).unwrap();
            s.put(Table::Cameras, "ext1", &serde_json::json!({"a": 1})).unwrap();
            s.put(Table::Cameras, "ext2", &serde_json::json!({"a": 2})).unwrap();
            assert!(s.delete(Table::Cameras, "ext2").unwrap());
        }
        let s = Store::open(dir.path()).unwrap();
        let rows: Vec<(String, serde_json::Value)> = s.list(Table::Cameras).unwrap();
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].0, "ext1");
        assert_eq!(rows[0].1["a"], 1);
    }
}
