//! The semantic table as SQLite (`semantic.sqlite`), for joins with a city database:
//!
//! ```sql
//! meta(key TEXT PRIMARY KEY, value TEXT)          -- run, scene, mode, query, rule, views, program
//! entities(id INTEGER PRIMARY KEY,                -- entity id of semantics.json (= city label id)
//!          object_id TEXT NOT NULL,               -- gml:id (join key with a 3DCityDB's cityobject.gmlid)
//!          class TEXT, level TEXT,                -- CityGML class; feature | surface | part
//!          parent_id INTEGER, building_id INTEGER, building_object_id TEXT,
//!          feature_id INTEGER, surface_id INTEGER, part_id INTEGER,  -- the ancestor chain (NULL = none)
//!          category TEXT,                         -- evaluation class (`docs/design.md`)
//!          gaussians INTEGER, gaussians_subtree INTEGER,  -- Gaussians labelled with it (and its descendants)
//!          pixels INTEGER, pixels_subtree INTEGER,        -- predicted pixels over the query's views
//!          selected INTEGER)                      -- 1 when the query selected it
//! attributes(entity_id INTEGER, name TEXT, value TEXT, number REAL, uom TEXT)
//!                                                 -- one row per value (lists: one row per element)
//! labels(id INTEGER PRIMARY KEY, source TEXT, entity_id INTEGER, group_id INTEGER, category TEXT,
//!        gaussians INTEGER, pixels INTEGER, selected INTEGER, relevancy REAL)
//! views(stem TEXT PRIMARY KEY, width INTEGER, height INTEGER, selected_pixels INTEGER)
//! ```
//! Written to a temporary file and renamed, so a failed write leaves no table behind.
use std::collections::HashMap;
use std::path::Path;

use rusqlite::{Connection, params};
use serde_json::Value;

use crate::classes;
use crate::labels::{LabelTable, Source};
use crate::semantics::{Entity, chains};

/// Errors of writing the table.
#[derive(Debug, thiserror::Error)]
pub enum SqliteError {
    #[error("{path}: SQLite: {err}")]
    Sql { path: String, err: rusqlite::Error },
    #[error("cannot write {path}: {err}")]
    Io { path: String, err: std::io::Error },
}

/// Everything the table holds besides the semantic table itself.
pub struct TableInputs<'a> {
    pub entities: &'a [Entity],
    pub labels: &'a LabelTable,
    /// Gaussians per label row (`labels.labels` order).
    pub gaussians: &'a [u64],
    /// Predicted pixels per label row over `views`.
    pub pixels: &'a [u64],
    /// Whether each label row is selected.
    pub selected_labels: &'a [bool],
    /// Whether each entity is selected.
    pub selected_entities: &'a [bool],
    /// Relevancy per label row of a text query.
    pub relevancy: Option<&'a [Option<f64>]>,
    /// `(stem, width, height, selected pixels)`.
    pub views: &'a [(String, usize, usize, u64)],
    pub meta: &'a [(&'a str, String)],
}

fn level_name(l: crate::citygml::Level) -> &'static str {
    match l {
        crate::citygml::Level::Feature => "feature",
        crate::citygml::Level::Surface => "surface",
        crate::citygml::Level::Part => "part",
    }
}

/// Writes the table to `path` (atomically).
pub fn write(path: &Path, t: &TableInputs<'_>) -> Result<(), SqliteError> {
    let tmp = path.with_extension("sqlite.tmp");
    let err = |err| SqliteError::Sql {
        path: path.display().to_string(),
        err,
    };
    let _ = std::fs::remove_file(&tmp);
    let _ = std::fs::remove_file(path);
    let result = (|| {
        let mut db = Connection::open(&tmp).map_err(err)?;
        fill(&mut db, t).map_err(err)?;
        db.close().map_err(|(_, e)| err(e))?;
        std::fs::rename(&tmp, path).map_err(|err| SqliteError::Io {
            path: path.display().to_string(),
            err,
        })
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

fn fill(db: &mut Connection, t: &TableInputs<'_>) -> rusqlite::Result<()> {
    db.execute_batch(
        "PRAGMA journal_mode = OFF; PRAGMA synchronous = OFF;
         CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT);
         CREATE TABLE entities(id INTEGER PRIMARY KEY, object_id TEXT NOT NULL, class TEXT, level TEXT,
             parent_id INTEGER REFERENCES entities(id), building_id INTEGER REFERENCES entities(id),
             building_object_id TEXT, feature_id INTEGER, surface_id INTEGER, part_id INTEGER,
             category TEXT, gaussians INTEGER, gaussians_subtree INTEGER, pixels INTEGER,
             pixels_subtree INTEGER, selected INTEGER);
         CREATE TABLE attributes(entity_id INTEGER REFERENCES entities(id), name TEXT, value TEXT,
             number REAL, uom TEXT);
         CREATE TABLE labels(id INTEGER PRIMARY KEY, source TEXT, entity_id INTEGER REFERENCES entities(id),
             group_id INTEGER, category TEXT, gaussians INTEGER, pixels INTEGER, selected INTEGER,
             relevancy REAL);
         CREATE TABLE views(stem TEXT PRIMARY KEY, width INTEGER, height INTEGER, selected_pixels INTEGER);",
    )?;
    let tx = db.transaction()?;
    {
        let mut s = tx.prepare("INSERT INTO meta VALUES (?1, ?2)")?;
        for (k, v) in t.meta {
            s.execute(params![k, v])?;
        }
    }
    // Per-entity counts: own label, then summed over descendants (parents precede children).
    let n = t.entities.len();
    let mut own_g = vec![0u64; n];
    let mut own_p = vec![0u64; n];
    let row_of: HashMap<i32, usize> = t
        .labels
        .labels
        .iter()
        .enumerate()
        .map(|(i, l)| (l.id, i))
        .collect();
    for (i, l) in t.labels.labels.iter().enumerate() {
        if let Some(e) = l
            .entity
            .and_then(|e| usize::try_from(e).ok())
            .filter(|&e| e < n)
        {
            own_g[e] += t.gaussians[i];
            own_p[e] += t.pixels[i];
        }
    }
    let (mut sub_g, mut sub_p) = (own_g.clone(), own_p.clone());
    for e in (0..n).rev() {
        if let Some(p) = t.entities[e]
            .parent
            .and_then(|p| usize::try_from(p).ok())
            .filter(|&p| p < e)
        {
            sub_g[p] += sub_g[e];
            sub_p[p] += sub_p[e];
        }
    }
    let chain = chains(t.entities);
    let opt = |x: i32| (x >= 0).then_some(x);
    {
        let mut s = tx.prepare(
            "INSERT INTO entities VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16)",
        )?;
        let mut a = tx.prepare("INSERT INTO attributes VALUES (?1, ?2, ?3, ?4, ?5)")?;
        for (i, e) in t.entities.iter().enumerate() {
            let b = usize::try_from(e.building)
                .ok()
                .and_then(|b| t.entities.get(b));
            s.execute(params![
                e.id,
                e.object_id,
                e.class.name(),
                level_name(e.level),
                e.parent,
                b.map(|b| b.id),
                b.map(|b| b.object_id.as_str()),
                opt(chain[i].feature),
                opt(chain[i].surface),
                opt(chain[i].part),
                classes::name(classes::of_entity(t.entities, i as i32)),
                own_g[i] as i64,
                sub_g[i] as i64,
                own_p[i] as i64,
                sub_p[i] as i64,
                t.selected_entities[i],
            ])?;
            for (k, v) in &e.attributes {
                if k.ends_with(".uom") {
                    continue;
                }
                let uom = e
                    .attributes
                    .get(&format!("{k}.uom"))
                    .and_then(|u| u.as_str());
                let mut put = |v: &Value| -> rusqlite::Result<()> {
                    let (text, num) = match v {
                        Value::String(s) => (Some(s.clone()), s.trim().parse::<f64>().ok()),
                        Value::Number(x) => (Some(x.to_string()), x.as_f64()),
                        Value::Null => (None, None),
                        v => (Some(v.to_string()), None),
                    };
                    a.execute(params![e.id, k, text, num, uom])?;
                    Ok(())
                };
                match v {
                    Value::Array(xs) => xs.iter().try_for_each(&mut put)?,
                    v => put(v)?,
                }
            }
        }
    }
    {
        let mut s = tx.prepare("INSERT INTO labels VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)")?;
        for (i, l) in t.labels.labels.iter().enumerate() {
            debug_assert_eq!(row_of[&l.id], i);
            s.execute(params![
                l.id,
                match l.source {
                    Source::City => "city",
                    Source::Image => "image",
                },
                l.entity,
                l.group,
                classes::name(l.class),
                t.gaussians[i] as i64,
                t.pixels[i] as i64,
                t.selected_labels[i],
                t.relevancy.and_then(|r| r[i]),
            ])?;
        }
    }
    {
        let mut s = tx.prepare("INSERT INTO views VALUES (?1, ?2, ?3, ?4)")?;
        for (stem, w, h, px) in t.views {
            s.execute(params![stem, *w as i64, *h as i64, *px as i64])?;
        }
    }
    tx.execute_batch(
        "CREATE INDEX entities_object_id ON entities(object_id);
         CREATE INDEX attributes_entity ON attributes(entity_id);
         CREATE INDEX attributes_name ON attributes(name);",
    )?;
    tx.commit()
}
