//! Overhangs: the area of a layer that does not rest on the layer below.
//!
//! A bead laid on the layer below may reach past its edge by a little (the slope a
//! wall may lean at without support); beyond that it is laid in mid-air. Step 1
//! ([`Overhang::reach_mm`]): the allowed reach of a layer of a given thickness. Step 2
//! ([`unsupported`]): the layer's islands less the layer below grown by the reach,
//! less strips narrower than [`OverhangOptions::min_width_mm`] (an opening by half of
//! it: what the contours' and offsets' chords leave, not an overhang). The first layer
//! rests on the bed.
//!
//! Pastes and slurries bridge far worse than molten plastic (no cooling sets them), so
//! the default allowed overhang is stricter than a plastic slicer's 45 degrees
//! ([`DEFAULT_OVERHANG_ANGLE_DEG`]).

use crate::geom::{area, difference, offset, Region, Shapes};
use serde::{Deserialize, Serialize};

/// The default allowed overhang (defined with the part's orientation, which is chosen
/// by it before any slice is cut).
pub use crate::mesh::orient::DEFAULT_OVERHANG_ANGLE_DEG;

/// How far a layer may reach past the layer below without support (`[process]
/// overhang`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Overhang {
    /// The steepest lean of a wall from vertical, degrees (0: nothing may reach past
    /// the layer below; Cura's "support overhang angle"; PrusaSlicer's threshold is
    /// 90 minus it).
    AngleDeg(f64),
    /// The farthest reach past the layer below, mm, whatever the layer's thickness.
    DistanceMm(f64),
}

impl Default for Overhang {
    fn default() -> Self {
        Overhang::AngleDeg(DEFAULT_OVERHANG_ANGLE_DEG)
    }
}

impl Overhang {
    /// How far a layer `thickness_mm` thick may reach past the layer below, mm.
    pub fn reach_mm(&self, thickness_mm: f64) -> f64 {
        match *self {
            Overhang::AngleDeg(a) => thickness_mm * a.to_radians().tan(),
            Overhang::DistanceMm(d) => d,
        }
    }

    /// The setting checked: an angle in [0, 89] degrees or a distance in [0, 10] mm;
    /// else what is wrong.
    pub fn check(&self) -> Result<(), String> {
        match *self {
            Overhang::AngleDeg(a) if !(0.0..=89.0).contains(&a) => Err(format!(
                "angle_deg = {a}: must be from 0 (no overhang) to 89 degrees from vertical"
            )),
            Overhang::DistanceMm(d) if !(0.0..=10.0).contains(&d) => {
                Err(format!("distance_mm = {d}: must be from 0 to 10 mm"))
            }
            _ => Ok(()),
        }
    }

    /// In words, for reports and warnings.
    pub fn describe(&self) -> String {
        match *self {
            Overhang::AngleDeg(a) => format!("{a} degrees from vertical"),
            Overhang::DistanceMm(d) => format!("{d} mm past the layer below"),
        }
    }
}

/// What [`unsupported`] needs besides the layers.
#[derive(Debug, Clone, Copy)]
pub struct OverhangOptions {
    pub overhang: Overhang,
    /// A strip narrower than this is not an overhang, mm (a job's: a quarter of the
    /// nozzle; it must exceed the chords' deviation).
    pub min_width_mm: f64,
    /// A piece smaller than this is not an overhang (a job's: the nozzle's square, a
    /// road's footprint, held by the beads around it; the corner a sharp edge leaves
    /// past a round reach is smaller), mm².
    pub min_area_mm2: f64,
    /// Chord of the offsets' round joins, mm.
    pub chord_mm: f64,
}

/// The shapes of `islands`.
pub fn shapes_of(islands: &[Region]) -> Shapes {
    islands
        .iter()
        .map(|r| {
            let mut shape = Vec::with_capacity(1 + r.holes.len());
            shape.push(r.outer.clone());
            shape.extend(r.holes.iter().cloned());
            shape
        })
        .collect()
}

/// The area of a layer (`islands`, `thickness_mm` thick) that does not rest on the
/// layer below (`below`; none: the bed) grown by the allowed reach, with what is
/// narrower than a road left out.
pub fn unsupported(
    islands: &[Region],
    below: Option<&[Region]>,
    thickness_mm: f64,
    opts: &OverhangOptions,
) -> Shapes {
    let Some(below) = below else {
        return Vec::new();
    };
    hanging(islands, &shapes_of(below), thickness_mm, opts)
}

/// [`unsupported`] on what lies below as shapes (the layer below and any support in it).
pub fn hanging(
    islands: &[Region],
    below: &Shapes,
    thickness_mm: f64,
    opts: &OverhangOptions,
) -> Shapes {
    let here = shapes_of(islands);
    if here.is_empty() {
        return Vec::new();
    }
    let reach = opts.overhang.reach_mm(thickness_mm);
    let resting = offset(below, reach, opts.chord_mm);
    let hanging = difference(&here, &resting);
    if hanging.is_empty() {
        return hanging;
    }
    let half = opts.min_width_mm / 2.0;
    let opened = offset(&offset(&hanging, -half, opts.chord_mm), half, opts.chord_mm);
    // The opening may round a corner past the hanging area; keep it within.
    let mut pieces = crate::geom::intersection(&opened, &hanging);
    retain_area_at_least(&mut pieces, opts.min_area_mm2);
    pieces
}

/// `shapes` less the pieces (a shape: its outer loop less its holes) under
/// `min_area_mm2`.
pub fn retain_area_at_least(shapes: &mut Shapes, min_area_mm2: f64) {
    shapes.retain(|piece| {
        let a: f64 = piece.iter().map(|l| crate::geom::signed_area(l)).sum();
        a.abs() >= min_area_mm2
    });
}

/// The unsupported area of each of `layers` (index, layer; bottom to top), in
/// parallel: none for a layer whose layer below is not among them (a range of layers
/// planned on its own); layer 0 rests on the bed.
pub fn of_layers(layers: &[(usize, &super::Layer)], opts: &OverhangOptions) -> Vec<Option<Shapes>> {
    use rayon::prelude::*;
    (0..layers.len())
        .into_par_iter()
        .map(|k| {
            let (index, layer) = layers[k];
            let below = match index {
                0 => None,
                _ => match k.checked_sub(1).map(|j| layers[j]) {
                    Some((i, below)) if i + 1 == index => Some(below.islands.as_slice()),
                    _ => return None,
                },
            };
            Some(unsupported(&layer.islands, below, layer.thickness_mm, opts))
        })
        .collect()
}

/// Layers with unsupported area over [`MIN_REPORTED_MM2`], as a short list: `3-7, 12`.
pub fn layer_list(layers: &[usize]) -> String {
    let mut out: Vec<String> = Vec::new();
    let mut k = 0;
    while k < layers.len() {
        let start = layers[k];
        let mut end = start;
        while k + 1 < layers.len() && layers[k + 1] == end + 1 {
            k += 1;
            end = layers[k];
        }
        out.push(if end == start {
            start.to_string()
        } else {
            format!("{start}-{end}")
        });
        k += 1;
    }
    out.join(", ")
}

/// The warning for people about `layers` (index, mm² resting on nothing); none when
/// there are none.
pub fn warning(allowed: &Overhang, layers: &[(usize, f64)]) -> Option<String> {
    let (worst, worst_mm2) = layers.iter().copied().max_by(|a, b| a.1.total_cmp(&b.1))?;
    let total: f64 = layers.iter().map(|l| l.1).sum();
    let indices: Vec<usize> = layers.iter().map(|l| l.0).collect();
    Some(format!(
        "{} layers have area resting on nothing beyond the allowed overhang ({}): layers \
         {} ({total:.2} mm² in all, the most {worst_mm2:.2} mm² at layer {worst}); a paste \
         laid there sags or drags: build supports ([support] mode), orient the part, or \
         allow more with [process] overhang",
        layers.len(),
        allowed.describe(),
        layer_list(&indices),
    ))
}

/// The refusal of a job with `[support] required` whose `layers` (index, mm²) rest on
/// nothing; none when there are none.
pub fn refusal(allowed: &Overhang, layers: &[(usize, f64)]) -> Option<String> {
    let w = warning(allowed, layers)?;
    Some(format!(
        "support.required: {w}; build supports under them ([support] mode = \
         \"everywhere\"), or orient the part ([geometry] orientation = \"auto\")"
    ))
}

/// Unsupported area below this is numerical dust, not an overhang, mm².
pub const MIN_REPORTED_MM2: f64 = 0.01;

/// The area of `shapes`, mm².
pub fn area_mm2(shapes: &Shapes) -> f64 {
    area(shapes).abs()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec2;

    fn square(lo: f64, hi: f64) -> Region {
        Region::new(
            vec![
                DVec2::new(lo, lo),
                DVec2::new(hi, lo),
                DVec2::new(hi, hi),
                DVec2::new(lo, hi),
            ],
            vec![],
        )
    }

    fn opts() -> OverhangOptions {
        OverhangOptions {
            overhang: Overhang::default(),
            min_width_mm: 0.1,
            min_area_mm2: 0.16,
            chord_mm: 0.005,
        }
    }

    #[test]
    fn a_layer_on_the_bed_or_within_the_reach_is_supported() {
        let layer = [square(0.0, 10.0)];
        assert!(unsupported(&layer, None, 0.2, &opts()).is_empty());
        // Leaning out by 0.1 mm a side on a 0.2 mm layer: tan 30 x 0.2 = 0.115 mm.
        let below = [square(0.1, 9.9)];
        let u = unsupported(&layer, Some(&below), 0.2, &opts());
        assert!(area_mm2(&u) < 1e-6, "{}", area_mm2(&u));
    }

    #[test]
    fn a_ledge_beyond_the_reach_is_found_and_slivers_are_not() {
        let layer = [square(0.0, 10.0)];
        // 2 mm short on every side: a ring 2 - 0.115 mm wide hangs.
        let below = [square(2.0, 8.0)];
        let u = unsupported(&layer, Some(&below), 0.2, &opts());
        let reach = 0.2 * 30f64.to_radians().tan();
        let inner = 6.0 + 2.0 * reach;
        let expected = 100.0 - inner * inner;
        assert!(
            (area_mm2(&u) - expected).abs() < 0.05 * expected,
            "{} against {expected}",
            area_mm2(&u)
        );
        // 0.2 mm short on every side: 0.085 mm past the reach, narrower than 0.1 mm.
        let below = [square(0.2, 9.8)];
        let u = unsupported(&layer, Some(&below), 0.2, &opts());
        assert!(area_mm2(&u) < 1e-6, "{}", area_mm2(&u));
        // 0.3 mm short: a 0.185 mm strip hangs all round (4 x 10 x 0.185 mm²).
        let below = [square(0.3, 9.7)];
        let u = unsupported(&layer, Some(&below), 0.2, &opts());
        assert!((area_mm2(&u) - 7.26).abs() < 0.2, "{}", area_mm2(&u));
        let below = [square(0.2, 9.8)];
        let u = unsupported(&layer, Some(&below), 0.2, &opts());
        assert!(area_mm2(&u) < 1e-6, "{}", area_mm2(&u));
        // The same by a distance: 0.5 mm allowed, nothing hangs.
        let by_distance = OverhangOptions {
            overhang: Overhang::DistanceMm(0.5),
            ..opts()
        };
        let below = [square(0.45, 9.55)];
        assert!(unsupported(&layer, Some(&below), 0.2, &by_distance).is_empty());
    }

    #[test]
    fn layer_lists_are_short() {
        assert_eq!(layer_list(&[3, 4, 5, 7, 9, 10]), "3-5, 7, 9-10");
        assert_eq!(layer_list(&[]), "");
    }

    #[test]
    fn settings_out_of_range_are_named() {
        assert!(Overhang::AngleDeg(90.0)
            .check()
            .unwrap_err()
            .contains("angle_deg"));
        assert!(Overhang::DistanceMm(-1.0)
            .check()
            .unwrap_err()
            .contains("distance_mm"));
        assert!(Overhang::default().check().is_ok());
    }
}
