//! The fused label space (`docs/design.md`, "Stage contract", `fuse/labels.json`): every label id
//! that a fused per-view map can hold, with where it comes from and its class.
//!
//! * City labels are the entity ids of `semantics.json` (`0 … E−1`), `source = "city"`.
//! * Image labels are associated mask groups, `id = group + Δ`, `source = "image"`, where
//!   `Δ` = the number of city entities rounded up to a power of ten, at least 10 000.
//!
//! Ids are `i32` everywhere (never 8- or 16-bit containers); an id that would overflow is an
//! error. This is a format module: it depends on no stage.
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::citygml::Level;
use crate::fsutil::{self, FsError};

/// Errors of the label table.
#[derive(Debug, thiserror::Error)]
pub enum LabelsError {
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error("label ids overflow int32: {0}")]
    Overflow(String),
    #[error(transparent)]
    Fs(#[from] FsError),
}

/// Where a label comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Source {
    /// A city-model entity (the `M_city` id of the raycast).
    City,
    /// A scene-consistent group of image masks (cross-view association).
    Image,
}

/// One label of the fused label space.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Label {
    pub id: i32,
    pub source: Source,
    /// City labels: the entity id (= `id`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub entity: Option<i32>,
    /// Image labels: the group id (= `id − Δ`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub group: Option<i32>,
    /// Evaluation class id (`docs/design.md`), −1 unknown.
    pub class: i32,
    /// City labels: the entity's hierarchy level; image labels: none.
    pub level: Option<Level>,
}

/// `labels.json`: `{"delta": Δ, "labels": [...]}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabelTable {
    pub delta: i32,
    pub labels: Vec<Label>,
    /// Row of each id (Fx hashing: looked up per pixel by the vote, fuse and eval; the map's
    /// order is never read).
    #[serde(skip)]
    index: rustc_hash::FxHashMap<i32, usize>,
}

/// The fused id of image group `group`: `group + Δ`; an error where it does not fit in `i32`.
pub fn image_id(delta: i32, group: usize) -> Result<i32, LabelsError> {
    i32::try_from(group)
        .ok()
        .and_then(|g| g.checked_add(delta))
        .ok_or_else(|| {
            LabelsError::Overflow(format!("group {group} + Δ = {delta} does not fit in int32"))
        })
}

/// `Δ` for `entities` city entities: the count rounded up to a power of ten, at least 10 000.
pub fn delta_for(entities: usize) -> Result<i32, LabelsError> {
    let mut d: i64 = 10_000;
    while d < entities as i64 {
        d *= 10;
    }
    i32::try_from(d).map_err(|_| {
        LabelsError::Overflow(format!(
            "{entities} city entities need an offset Δ = {d} > 2^31"
        ))
    })
}

impl LabelTable {
    /// A table from its parts (checks ids are unique and consistent with their source).
    pub fn new(delta: i32, labels: Vec<Label>) -> Result<LabelTable, String> {
        let mut index =
            rustc_hash::FxHashMap::with_capacity_and_hasher(labels.len(), Default::default());
        for (i, l) in labels.iter().enumerate() {
            if index.insert(l.id, i).is_some() {
                return Err(format!("label id {} is listed twice", l.id));
            }
            let ok = match l.source {
                Source::City => l.id >= 0 && l.id < delta && l.entity == Some(l.id),
                Source::Image => {
                    l.id >= delta
                        && l.group.map(|g| i64::from(g) + i64::from(delta)) == Some(i64::from(l.id))
                }
            };
            if !ok {
                return Err(format!(
                    "label {} ({:?}) is inconsistent with Δ = {delta} and its entity/group",
                    l.id, l.source
                ));
            }
        }
        Ok(LabelTable {
            delta,
            labels,
            index,
        })
    }

    /// The city-only table: one label per entity, with the class of `classes[entity]`.
    pub fn city(
        entities: &[crate::semantics::Entity],
        classes: &[i32],
    ) -> Result<LabelTable, LabelsError> {
        let delta = delta_for(entities.len())?;
        let labels = entities
            .iter()
            .enumerate()
            .map(|(i, e)| Label {
                id: i as i32,
                source: Source::City,
                entity: Some(i as i32),
                group: None,
                class: classes.get(i).copied().unwrap_or(-1),
                level: Some(e.level),
            })
            .collect();
        LabelTable::new(delta, labels).map_err(LabelsError::Overflow)
    }

    /// The fused table: one label per entity (class `classes[entity]`), then one image label per
    /// group `g` with id `g + Δ` and class `group_classes[g]`. An id beyond `i32` is an error.
    pub fn fused(
        entities: &[crate::semantics::Entity],
        classes: &[i32],
        group_classes: &[i32],
    ) -> Result<LabelTable, LabelsError> {
        let city = LabelTable::city(entities, classes)?;
        let delta = city.delta;
        let mut labels = city.labels;
        labels.reserve(group_classes.len());
        if let Some(last) = group_classes.len().checked_sub(1) {
            image_id(delta, last)?;
        }
        for (g, &class) in group_classes.iter().enumerate() {
            let id = image_id(delta, g)?;
            labels.push(Label {
                id,
                source: Source::Image,
                entity: None,
                group: Some(id - delta),
                class,
                level: None,
            });
        }
        LabelTable::new(delta, labels).map_err(LabelsError::Overflow)
    }

    /// The label with id `id`.
    pub fn get(&self, id: i32) -> Option<&Label> {
        self.index.get(&id).map(|&i| &self.labels[i])
    }

    /// The row of label `id` in [`LabelTable::labels`] (the row of its features).
    pub fn row(&self, id: i32) -> Option<usize> {
        self.index.get(&id).copied()
    }

    /// The class of label `id` (−1 for −1 and unknown ids).
    pub fn class_of(&self, id: i32) -> i32 {
        self.get(id).map_or(-1, |l| l.class)
    }

    /// Reads `labels.json`.
    pub fn read(path: &Path) -> Result<LabelTable, LabelsError> {
        #[derive(Deserialize)]
        struct File {
            delta: i32,
            labels: Vec<Label>,
        }
        let f: File = fsutil::read_json(path)?;
        LabelTable::new(f.delta, f.labels).map_err(|why| LabelsError::Invalid {
            path: path.to_path_buf(),
            why,
        })
    }

    /// Writes `labels.json` atomically.
    pub fn write(&self, path: &Path) -> Result<(), LabelsError> {
        fsutil::write_json(path, self)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn delta_is_a_power_of_ten_at_least_ten_thousand() {
        assert_eq!(delta_for(0).unwrap(), 10_000);
        assert_eq!(delta_for(10_000).unwrap(), 10_000);
        assert_eq!(delta_for(10_001).unwrap(), 100_000);
        assert_eq!(delta_for(70_000).unwrap(), 100_000);
        assert!(
            delta_for(1_000_000_001)
                .unwrap_err()
                .to_string()
                .contains("2^31")
        );
    }

    #[test]
    fn ids_must_match_their_source() {
        let city = |id| Label {
            id,
            source: Source::City,
            entity: Some(id),
            group: None,
            class: 0,
            level: Some(Level::Surface),
        };
        let image = |g| Label {
            id: 10_000 + g,
            source: Source::Image,
            entity: None,
            group: Some(g),
            class: 8,
            level: None,
        };
        let t = LabelTable::new(10_000, vec![city(0), city(1), image(0), image(5)]).unwrap();
        assert_eq!(t.class_of(10_005), 8);
        assert_eq!(t.class_of(1), 0);
        assert_eq!(t.class_of(-1), -1);
        assert!(LabelTable::new(10_000, vec![city(0), city(0)]).is_err());
        assert!(LabelTable::new(10_000, vec![city(10_000)]).is_err());
        let mut bad = image(3);
        bad.id = 10_004;
        assert!(LabelTable::new(10_000, vec![bad]).is_err());
    }

    #[test]
    fn fused_table_offsets_groups_by_delta_and_refuses_overflow() {
        let e = |id: i32| crate::semantics::Entity {
            id,
            object_id: format!("e{id}"),
            class: crate::semantics::Class::WallSurface,
            level: Level::Surface,
            parent: None,
            building: 0,
            source: String::new(),
            lod: Some(3),
            attributes: Default::default(),
        };
        let ents = vec![e(0), e(1)];
        let t = LabelTable::fused(&ents, &[0, 2], &[8, 11, 6]).unwrap();
        assert_eq!(t.delta, 10_000);
        assert_eq!(t.labels.len(), 5);
        assert_eq!(t.class_of(1), 2);
        assert_eq!(t.class_of(10_002), 6);
        assert_eq!(t.get(10_001).unwrap().group, Some(1));
        assert_eq!(t.get(10_001).unwrap().source, Source::Image);
        // The last group that fits after Δ = 10 000 is 2^31 − 1 − 10 000.
        let last = (i32::MAX - 10_000) as usize;
        assert_eq!(image_id(10_000, last).unwrap(), i32::MAX);
        let err = image_id(10_000, last + 1).unwrap_err();
        assert!(err.to_string().contains("int32"), "{err}");
    }
}
