//! The decision rules on one view's SAM list (module docs of `masks`, "rules"): quality and
//! area, `R_ov` against the building support, the features test, the depth test and the
//! low-overlap check → a kept mask or a dropped one, each with its [`Rule`] and the scores it used.
use std::collections::BTreeMap;

use super::geometry::{MaskCounts, ViewCodes, ratio};
use super::prompts::FeatureScores;
use super::{MasksError, Plan, Test};
use crate::maskfile::{Decision, KeptMask, Rule};
use crate::sam::SamMask;

/// The rules on a SAM list.
pub(super) fn decide_sam(
    plan: &Plan<'_>,
    codes: &ViewCodes,
    list: &[SamMask],
    features: Option<&[f32]>,
    min_area: u64,
) -> Result<(Vec<KeptMask>, Vec<Decision>), MasksError> {
    let mut kept = Vec::new();
    let mut decisions = Vec::with_capacity(list.len());
    for (i, m) in list.iter().enumerate() {
        let runs = m.segmentation.counts().expect("validated by read_sam_json");
        let c = codes.count(&runs);
        let fs = match (&plan.prompts, features) {
            (Some(p), Some(f)) => Some(p.score(&f[i * p.dim..(i + 1) * p.dim])),
            _ => None,
        };
        let mut scores = BTreeMap::new();
        scores.insert("predicted_iou".to_string(), m.predicted_iou);
        scores.insert("area".to_string(), m.area as f64);
        if let Some(f) = &fs {
            scores.insert("s_city".into(), f.s_city);
            scores.insert("s_fore".into(), f.s_fore);
            scores.insert("class".into(), f.class as f64);
            scores.insert("class_margin".into(), f.margin);
        }
        if plan.depth_used() {
            scores.insert("evidence_share".into(), ratio(c.evidence(), c.area));
            scores.insert("front_share".into(), c.front_share());
            scores.insert("surface_share".into(), c.surface_share());
            scores.insert("behind_share".into(), c.behind_share());
        }
        let rule = rule_for(plan, m, &c, fs.as_ref(), min_area);
        let keep = rule.keeps();
        let r_ov = c.r_ov();
        if keep {
            kept.push(KeptMask {
                sam: m.clone(),
                source_index: i as i64,
                r_ov,
                rule,
                class: fs.map_or(crate::classes::NONE, |f| f.class),
            });
        }
        decisions.push(Decision {
            source_index: i as i64,
            kept: keep,
            rule,
            r_ov,
            scores,
        });
    }
    Ok((kept, decisions))
}

/// The decision on one SAM mask (see the module docs): its rule, which keeps it when
/// [`Rule::keeps`].
fn rule_for(
    plan: &Plan<'_>,
    m: &SamMask,
    c: &MaskCounts,
    fs: Option<&FeatureScores>,
    min_area: u64,
) -> Rule {
    let opts = plan.opts;
    if m.predicted_iou < opts.tau_q {
        // Support-only: the other rules decide whether it is a foreground candidate at all.
        if opts.support_floor.is_some_and(|f| m.predicted_iou >= f)
            && rule_after_quality(plan, m, c, fs, min_area).keeps()
        {
            return Rule::LowQualitySupport;
        }
        return Rule::Quality;
    }
    rule_after_quality(plan, m, c, fs, min_area)
}

/// [`rule_for`] from the area rule on (the quality rule passed or set aside).
fn rule_after_quality(
    plan: &Plan<'_>,
    m: &SamMask,
    c: &MaskCounts,
    fs: Option<&FeatureScores>,
    min_area: u64,
) -> Rule {
    let opts = plan.opts;
    if m.area < min_area {
        return Rule::Area;
    }
    // Features decide only in the tests that use them (they still give the class).
    let fs = fs.filter(|_| matches!(plan.test, Test::Features | Test::Both));
    let evidence = plan.depth_used() && ratio(c.evidence(), c.area) >= opts.min_evidence;
    let occluder = evidence && c.front_share() >= opts.occluder_share;
    let features_fore = fs.map(|f| f.s_fore > f.s_city + opts.delta);
    let features_city = fs.map(|f| f.s_city > f.s_fore + opts.delta);
    if c.r_ov() < opts.rho {
        if opts.low_overlap_check {
            // Decisive features decide; the depth decides where they are not (or absent).
            let building = match (features_city, features_fore) {
                (Some(true), _) => true,
                (_, Some(true)) => false,
                _ => evidence && c.front_share() < opts.occluder_share,
            };
            if building {
                return Rule::LowOverlapBuilding;
            }
        }
        return Rule::LowOverlap;
    }
    match plan.test {
        Test::Features => {
            if features_fore == Some(true) {
                Rule::FeaturesForeground
            } else {
                Rule::FeaturesBuilding
            }
        }
        Test::Geometry => {
            if occluder {
                Rule::Occluder
            } else if evidence {
                Rule::OnSurface
            } else {
                Rule::NoDepth
            }
        }
        Test::Both => {
            if occluder && features_city != Some(true) {
                Rule::OccluderAndFeatures
            } else if !evidence && features_fore == Some(true) {
                Rule::FeaturesForeground
            } else if occluder {
                Rule::FeaturesBuilding
            } else if evidence {
                Rule::OnSurface
            } else {
                Rule::NoDepth
            }
        }
        Test::Overlap | Test::Auto => Rule::HighOverlap,
    }
}
