//! The filters (paper §3.2; step 4 of docs/associate.md) and the numbering of the kept groups:
//! a group seen in fewer than `m_view` views — counting its view support — is dropped, and so
//! is a far-field group, whose weighted centroid lies farther than the far-field distance from
//! every camera. The kept groups are numbered in canonical order and get their `groups.json`
//! record and unit mean feature.
use std::collections::BTreeSet;

use super::{Stage, Tally, bank};
use crate::camera::View;
use crate::groups::GroupRecord;

/// Each pre-filter group's distance to the nearest camera, and the far-field limit.
pub(super) struct FarField {
    /// Per pre-filter group: the distance from its centroid to the nearest camera.
    pub(super) nearest: Vec<f64>,
    /// The far-field distance in scene units (metres × alignment scale).
    limit: f64,
}

impl FarField {
    /// The distances of `fin`'s groups to the cameras of `views`; `limit` in scene units.
    pub(super) fn new(fin: &bank::Finished, views: &[&View], limit: f64) -> FarField {
        let cams: Vec<glam::DVec3> = views.iter().map(|v| v.camera.pose.center()).collect();
        let nearest: Vec<f64> = fin
            .groups
            .iter()
            .map(|g| {
                let c = glam::DVec3::from_array(g.centroid);
                cams.iter()
                    .map(|k| (*k - c).length())
                    .fold(f64::INFINITY, f64::min)
            })
            .collect();
        FarField { nearest, limit }
    }

    /// Whether pre-filter group `gi` is far field (or its distance is unknown).
    pub(super) fn is_far(&self, gi: usize) -> bool {
        self.nearest[gi].is_nan() || self.nearest[gi] > self.limit
    }
}

/// The groups that pass the filters.
pub(super) struct Kept {
    /// Kept group id per pre-filter group, −1 for a dropped group.
    pub(super) id: Vec<i32>,
    /// The kept groups' `groups.json` records, by id.
    pub(super) records: Vec<GroupRecord>,
    /// Their unit mean features (G×D, row-major; zero rows where none), when the masks have
    /// features.
    pub(super) features: Vec<f32>,
}

/// The `m_view` and far-field filters over the pre-filter groups of `fin`, with the view
/// `support` (per group, the views where dropped masks match it) counted towards `m_view`; the
/// kept groups are numbered in canonical order. The counts go to `tally`.
pub(super) fn keep_groups(
    st: &Stage<'_>,
    fin: &bank::Finished,
    support: &[BTreeSet<u32>],
    far: &FarField,
    tally: &mut Tally,
) -> Kept {
    let (opts, views, dim) = (st.opts, st.views, tally.dim);
    let (mut dropped_views, mut dropped_far, mut supported) = (0, 0, 0);
    let mut keep_id: Vec<i32> = vec![-1; fin.groups.len()];
    let mut records = Vec::new();
    let mut group_features: Vec<f32> = Vec::new();
    for (gi, g) in fin.groups.iter().enumerate() {
        if g.views.len() + support[gi].len() < opts.min_views {
            dropped_views += 1;
            continue;
        }
        if far.is_far(gi) {
            dropped_far += 1;
            continue;
        }
        if g.views.len() < opts.min_views {
            supported += 1;
        }
        let id = records.len() as i32;
        keep_id[gi] = id;
        if let Some(d) = dim {
            let norm = g.feature_mean.iter().map(|x| x * x).sum::<f64>().sqrt();
            if g.feature_mean.len() == d && norm > 0.0 {
                group_features.extend(g.feature_mean.iter().map(|&x| (x / norm) as f32));
            } else {
                group_features.extend(std::iter::repeat_n(0.0f32, d));
            }
        }
        records.push(GroupRecord {
            id,
            views: g.views.iter().map(|&v| views[v as usize].stem()).collect(),
            support_views: support[gi]
                .iter()
                .map(|&v| views[v as usize].stem())
                .collect(),
            masks: g.members.len(),
            pixels: g.pixels,
            gaussians: g.gaussians,
            class: g.class,
            centroid: g.centroid,
            nearest_camera_distance: far.nearest[gi],
        });
    }
    let masks_dropped = fin.group_of.iter().filter(|&&gi| keep_id[gi] < 0).count();
    tally.dropped_views = dropped_views;
    tally.dropped_far = dropped_far;
    tally.supported = supported;
    tally.masks_dropped = masks_dropped;
    Kept {
        id: keep_id,
        records,
        features: group_features,
    }
}
