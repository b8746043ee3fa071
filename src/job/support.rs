//! `[support]` validated: the mode, what supports are built of, and the settings
//! slicers' users know, defaults resolved (`docs/job-format.md`).

use super::{LayerHeights, RawSupport, Support, SupportMaterial};
use crate::slice::support::{SupportArea, SupportAreaOptions, SupportMode};
use crate::toolpath::support::{SupportPattern, SupportRoads};

/// The most interface layers a column may have.
const MAX_INTERFACE_LAYERS: u32 = 20;
/// The widest gap a setting may ask for, mm.
const MAX_GAP_MM: f64 = 10.0;

/// `[support]` checked against the job's materials, layers and road width.
pub(super) fn support<E>(
    raw: RawSupport,
    materials: &[String],
    layers: &LayerHeights,
    road_width_mm: f64,
    bad: &impl Fn(&str, String) -> E,
) -> Result<Support, E> {
    let mode = match raw.mode.as_deref() {
        None | Some("off") => SupportMode::Off,
        Some("buildplate") => SupportMode::Buildplate,
        Some("everywhere") => SupportMode::Everywhere,
        Some(other) => {
            return Err(bad(
                "support.mode",
                format!("\"{other}\": must be \"off\", \"buildplate\" or \"everywhere\""),
            ))
        }
    };
    let material = support_material(&raw, materials, mode, bad)?;
    // A fugitive ink is laid on and washed out; a part material would fuse without a
    // gap of a layer.
    let default_gap = match material {
        Some(SupportMaterial::Composition(_)) => layers.max_mm,
        _ => 0.0,
    };
    let gap = |v: Option<f64>, key: &str, default: f64| -> Result<f64, E> {
        let v = v.unwrap_or(default);
        if !v.is_finite() || !(0.0..=MAX_GAP_MM).contains(&v) {
            return Err(bad(
                key,
                format!("must be a length from 0 to {MAX_GAP_MM} mm, got {v}"),
            ));
        }
        Ok(v)
    };
    let top_gap_mm = gap(raw.top_gap_mm, "support.top_gap_mm", default_gap)?;
    let bottom_gap_mm = gap(raw.bottom_gap_mm, "support.bottom_gap_mm", top_gap_mm)?;
    // Likewise beside the part: a fugitive ink touches it, a part material keeps half
    // a road off.
    let default_xy = match material {
        Some(SupportMaterial::Composition(_)) => road_width_mm / 2.0,
        _ => 0.0,
    };
    let xy_gap_mm = gap(raw.xy_gap_mm, "support.xy_gap_mm", default_xy)?;
    let interface_layers = raw
        .interface_layers
        .unwrap_or(super::DEFAULT_INTERFACE_LAYERS);
    if interface_layers > MAX_INTERFACE_LAYERS {
        return Err(bad(
            "support.interface_layers",
            format!("must be from 0 to {MAX_INTERFACE_LAYERS}, got {interface_layers}"),
        ));
    }
    let pattern = match raw.pattern.as_deref() {
        None | Some("lines") => SupportPattern::Lines,
        Some("grid") => SupportPattern::Grid,
        Some(other) => {
            return Err(bad(
                "support.pattern",
                format!("\"{other}\": must be \"lines\" or \"grid\""),
            ))
        }
    };
    let density = raw.density.unwrap_or(super::DEFAULT_SUPPORT_DENSITY);
    if !density.is_finite() || !(0.05..=1.0).contains(&density) {
        return Err(bad(
            "support.density",
            format!(
                "must be a fraction from 0.05 to 1 (the base's area laid with road), got {density}"
            ),
        ));
    }
    let angle_deg = raw.angle_deg.unwrap_or(0.0);
    if !angle_deg.is_finite() || !(-360.0..=360.0).contains(&angle_deg) {
        return Err(bad(
            "support.angle_deg",
            format!("must be an angle from -360 to 360 degrees, got {angle_deg}"),
        ));
    }
    Ok(Support {
        required: raw.required,
        mode,
        material,
        top_gap_mm,
        bottom_gap_mm,
        xy_gap_mm,
        interface_layers,
        pattern,
        density,
        angle_deg,
    })
}

/// `support.syringe` or `support.composition`: exactly one when supports are built.
fn support_material<E>(
    raw: &RawSupport,
    materials: &[String],
    mode: SupportMode,
    bad: &impl Fn(&str, String) -> E,
) -> Result<Option<SupportMaterial>, E> {
    let material = match (&raw.syringe, &raw.composition) {
        (Some(_), Some(_)) => {
            return Err(bad(
                "support",
                "give syringe (a support ink of its own) or composition (the part's \
                 materials), not both"
                    .to_string(),
            ))
        }
        (Some(name), None) => {
            super::check_name(name).map_err(|m| bad("support.syringe", m))?;
            if materials.contains(name) {
                return Err(bad(
                    "support.syringe",
                    format!(
                        "\"{name}\" is one of the part's materials; for supports of the \
                         part's materials give support.composition"
                    ),
                ));
            }
            Some(SupportMaterial::Syringe(name.clone()))
        }
        (None, Some(c)) => Some(SupportMaterial::Composition(support_composition(
            c, materials, bad,
        )?)),
        (None, None) => None,
    };
    if mode != SupportMode::Off && material.is_none() {
        return Err(bad(
            "support",
            format!(
                "mode = \"{}\" needs what supports are built of: syringe = \"<name>\" (a \
                 syringe of the machine with role = \"support\", such as a fugitive ink) \
                 or composition = [...] (fractions of {})",
                mode.name(),
                materials.join(", ")
            ),
        ));
    }
    Ok(material)
}

/// `support.composition`: one fraction per material, each from 0 to 1, summing to 1.
fn support_composition<E>(
    c: &[f64],
    materials: &[String],
    bad: &impl Fn(&str, String) -> E,
) -> Result<Vec<f64>, E> {
    let key = "support.composition";
    if c.len() != materials.len() {
        return Err(bad(
            key,
            format!(
                "{} fractions for {} materials ({}): give one per material",
                c.len(),
                materials.len(),
                materials.join(", ")
            ),
        ));
    }
    if c.iter().any(|f| !f.is_finite() || !(0.0..=1.0).contains(f)) {
        return Err(bad(
            key,
            format!("{c:?}: each fraction must be from 0 to 1"),
        ));
    }
    let sum: f64 = c.iter().sum();
    if (sum - 1.0).abs() > 1e-6 {
        return Err(bad(
            key,
            format!("{c:?}: the fractions sum to {sum}, not 1"),
        ));
    }
    Ok(c.to_vec())
}

/// How the job's support roads are built (none when supports are off): in the
/// support syringe's own channel after the part's materials, or at the composition.
pub(super) fn support_roads(support: &Support, materials: usize) -> Option<SupportRoads> {
    if !support.builds() {
        return None;
    }
    let composition = match support.material.as_ref()? {
        SupportMaterial::Syringe(_) => {
            let mut c = vec![0.0; materials + 1];
            c[materials] = 1.0;
            c
        }
        SupportMaterial::Composition(c) => c.clone(),
    };
    Some(SupportRoads {
        pattern: support.pattern,
        density: support.density,
        angle_deg: support.angle_deg,
        composition,
    })
}

impl super::Job {
    /// What finding this job's support areas needs (none when supports are off): its
    /// gaps and interface, its overhangs found as warnings find them, each column a
    /// road and the XY gap wider than its overhang (so a strip of overhang beside the
    /// part still gets a road beyond the gap), pieces narrower than a road left out.
    pub fn support_area_options(&self) -> Option<SupportAreaOptions> {
        if !self.support.builds() {
            return None;
        }
        Some(SupportAreaOptions {
            mode: self.support.mode,
            top_gap_mm: self.support.top_gap_mm,
            bottom_gap_mm: self.support.bottom_gap_mm,
            xy_gap_mm: self.support.xy_gap_mm,
            interface_layers: self.support.interface_layers as usize,
            overhang: self.overhang_options(),
            min_width_mm: self.toolpath.road_width(),
            expansion_mm: self.toolpath.road_width() + self.support.xy_gap_mm,
        })
    }
}

/// A mesh part's supports: each layer's area, and what still rests on nothing with
/// them (layer index and mm², over [`crate::slice::overhang::MIN_REPORTED_MM2`]).
pub struct PartSupports {
    pub areas: Vec<SupportArea>,
    pub still_hanging: Vec<(usize, f64)>,
    /// What rests on nothing without them, all layers, mm².
    pub without_mm2: f64,
}

impl super::MeshLayers {
    /// With `job`'s `[support]` on, the part's supports (none when off). The whole
    /// stack is cut at once: a layer's support depends on every layer above it, so
    /// memory holds the part's sections (not its roads) while they are found.
    pub fn supports(
        &self,
        job: &super::Job,
    ) -> Result<Option<PartSupports>, crate::slice::SliceError> {
        use crate::slice::overhang::{area_mm2, of_layers, MIN_REPORTED_MM2};
        use crate::slice::support::{support_areas, unsupported_with_support, StackLayer};
        let Some(opts) = job.support_area_options() else {
            return Ok(None);
        };
        let (layers, _) = self.cut(0..self.len(), None)?;
        let indexed: Vec<(usize, &crate::slice::Layer)> = layers.iter().enumerate().collect();
        let overhangs: Vec<crate::geom::Shapes> = of_layers(&indexed, &opts.overhang)
            .into_iter()
            .map(Option::unwrap_or_default)
            .collect();
        let stack: Vec<StackLayer> = layers
            .iter()
            .map(|l| StackLayer {
                z_mm: l.z_mm,
                thickness_mm: l.thickness_mm,
                islands: &l.islands,
            })
            .collect();
        let areas = support_areas(&stack, &overhangs, &opts);
        let still_hanging =
            unsupported_with_support(&stack, &areas, &overhangs, opts.top_gap_mm, &opts.overhang)
                .iter()
                .map(area_mm2)
                .enumerate()
                .filter(|(_, a)| *a > MIN_REPORTED_MM2)
                .collect();
        Ok(Some(PartSupports {
            areas,
            still_hanging,
            without_mm2: overhangs.iter().map(area_mm2).sum(),
        }))
    }
}

#[cfg(test)]
mod tests {
    use crate::job::{Job, JobError};

    const JOB: &str = "name = \"s\"\n[geometry]\npolygon = { outer = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]] }\nheight = 1.0\n[materials]\nnames = [\"A\", \"B\"]\n[gradient]\ninner = [1.0, 0.0]\nouter = [0.0, 1.0]\n[process]\nr_mach = 1.0\nnozzle = 0.4\nlayer = 0.2\n";

    fn parse(support: &str) -> Result<Job, JobError> {
        Job::from_toml(&format!("{JOB}[support]\n{support}\n"), "s.toml")
    }

    #[test]
    fn supports_default_by_what_they_are_built_of() {
        let j = parse("mode = \"everywhere\"\nsyringe = \"S\"").unwrap();
        assert_eq!(j.support.syringe(), Some("S"));
        assert_eq!((j.support.top_gap_mm, j.support.xy_gap_mm), (0.0, 0.0));
        let roads = j.toolpath.support.as_ref().unwrap();
        assert_eq!(roads.composition, vec![0.0, 0.0, 1.0]);
        assert_eq!(j.toolpath.channels(), Some(3));
        let j = parse("mode = \"buildplate\"\ncomposition = [0.5, 0.5]").unwrap();
        assert_eq!((j.support.top_gap_mm, j.support.xy_gap_mm), (0.2, 0.2));
        assert_eq!(j.toolpath.channels(), Some(2));
        // Off: nothing planned, whatever else is said.
        let j = parse("syringe = \"S\"").unwrap();
        assert!(j.toolpath.support.is_none() && j.support.syringe().is_none());
    }

    #[test]
    fn wrong_support_settings_are_named() {
        for (text, key) in [
            ("mode = \"sometimes\"", "support.mode"),
            ("mode = \"everywhere\"", "support"),
            (
                "mode = \"everywhere\"\nsyringe = \"S\"\ncomposition = [1.0, 0.0]",
                "support",
            ),
            ("mode = \"everywhere\"\nsyringe = \"A\"", "support.syringe"),
            (
                "mode = \"everywhere\"\ncomposition = [0.5, 0.6]",
                "support.composition",
            ),
            (
                "mode = \"everywhere\"\ncomposition = [1.0]",
                "support.composition",
            ),
            (
                "mode = \"everywhere\"\nsyringe = \"S\"\ndensity = 0.0",
                "support.density",
            ),
            (
                "mode = \"everywhere\"\nsyringe = \"S\"\npattern = \"gyroid\"",
                "support.pattern",
            ),
            (
                "mode = \"everywhere\"\nsyringe = \"S\"\ntop_gap_mm = -1.0",
                "support.top_gap_mm",
            ),
            (
                "mode = \"everywhere\"\nsyringe = \"S\"\ninterface_layers = 99",
                "support.interface_layers",
            ),
        ] {
            match parse(text) {
                Err(JobError::Invalid { key: k, .. }) => assert_eq!(k, key, "{text}"),
                other => panic!("{text}: {other:?}"),
            }
        }
    }
}
