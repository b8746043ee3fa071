//! Supports: where each layer needs something under the part's overhangs.
//!
//! The part's overhangs ([`super::overhang::unsupported`]) are held up by columns that
//! go straight down from each overhang, one [`SupportAreaOptions::top_gap_mm`] below
//! it, until they meet the part (with [`SupportMode::Everywhere`]: they rest on it,
//! [`SupportAreaOptions::bottom_gap_mm`] above it) or the bed. With
//! [`SupportMode::Buildplate`] a column that would meet the part is left out whole, as
//! PrusaSlicer's "support on build plate only" does. Steps:
//!
//! 1. Each layer's area resting on nothing ([`super::overhang::of_layers`], the
//!    caller's: the same the warnings name).
//! 2. [`part_shadows`] (build plate only): the union of every layer below each layer,
//!    where a column would land on the part.
//! 3. [`support_areas`]: top down, the columns carried from above plus the overhangs
//!    released at this layer, less the part (a column ends on it), less the part grown
//!    by [`SupportAreaOptions::xy_gap_mm`]; the top
//!    [`SupportAreaOptions::interface_layers`] under each overhang are the dense
//!    interface the part is laid on ([`SupportArea::interface`]), the rest the sparse
//!    base ([`SupportArea::base`]).
//!
//! The roads that build these areas are `toolpath::support`'s.

use super::overhang::{hanging, retain_area_at_least, shapes_of, OverhangOptions};
use crate::geom::{difference, intersection, offset, union, Region, Shapes};
use serde::{Deserialize, Serialize};

/// `[support] mode`: whether supports are built, and what they may rest on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SupportMode {
    /// No supports: overhangs are reported and warned of (the default).
    #[default]
    Off,
    /// Supports only where they stand on the bed; overhangs above the part stay
    /// unsupported (and are warned of).
    Buildplate,
    /// Supports under every overhang, standing on the bed or on the part.
    Everywhere,
}

impl SupportMode {
    /// The name the job file uses.
    pub fn name(self) -> &'static str {
        match self {
            SupportMode::Off => "off",
            SupportMode::Buildplate => "buildplate",
            SupportMode::Everywhere => "everywhere",
        }
    }
}

/// What [`support_areas`] needs besides the layers.
#[derive(Clone, Copy, Debug)]
pub struct SupportAreaOptions {
    /// Buildplate or everywhere ([`SupportMode::Off`] gives no areas).
    pub mode: SupportMode,
    /// Vertical gap from the top of a column to the overhang it holds, mm (0: the
    /// part is laid on the support, as with a fugitive ink washed out afterwards).
    pub top_gap_mm: f64,
    /// Vertical gap from the part's top to a column standing on it, mm.
    pub bottom_gap_mm: f64,
    /// Horizontal gap from the support to the part in the same layer, mm.
    pub xy_gap_mm: f64,
    /// Dense layers at the top of each column.
    pub interface_layers: usize,
    /// How the part's overhangs are found.
    pub overhang: OverhangOptions,
    /// A support piece narrower than this is left out (it could not take one road),
    /// mm: an opening by half of it.
    pub min_width_mm: f64,
    /// Each overhang's column is this much wider than the overhang, mm (a strip of
    /// overhang narrower than a road beside the part still gets a column a road wide
    /// beyond the XY gap).
    pub expansion_mm: f64,
}

/// One layer of the part as supports see it.
#[derive(Clone, Copy, Debug)]
pub struct StackLayer<'a> {
    /// Top of the layer, mm.
    pub z_mm: f64,
    pub thickness_mm: f64,
    pub islands: &'a [Region],
}

impl StackLayer<'_> {
    fn bottom_mm(&self) -> f64 {
        self.z_mm - self.thickness_mm
    }
}

/// The support to build in one layer, beside the part.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SupportArea {
    /// The sparse body of the columns.
    pub base: Shapes,
    /// The dense top layers of the columns, right under the part.
    pub interface: Shapes,
}

impl SupportArea {
    /// Whether there is no support in the layer.
    pub fn is_empty(&self) -> bool {
        self.base.is_empty() && self.interface.is_empty()
    }

    /// Base and interface together.
    pub fn all(&self) -> Shapes {
        let mut all = self.base.clone();
        all.extend(self.interface.iter().cloned());
        all
    }
}

/// Heights are compared to this, mm.
const Z_EPS_MM: f64 = 1e-6;

/// Step 2: for each layer, the union of the part in every layer below it.
pub fn part_shadows(stack: &[StackLayer]) -> Vec<Shapes> {
    let mut out = Vec::with_capacity(stack.len());
    let mut shadow: Shapes = Vec::new();
    for layer in stack {
        out.push(shadow.clone());
        let here = shapes_of(layer.islands);
        shadow = if shadow.is_empty() {
            here
        } else {
            union(&shadow, &here)
        };
    }
    out
}

/// The layer whose support holds up a layer whose bottom is at `bottom_mm` (the
/// highest whose top is at or under it less `top_gap_mm`), searching down from
/// `below` (the layer under it); `top_of(k)` is layer k's top, mm.
pub fn holding_layer(
    below: usize,
    bottom_mm: f64,
    top_gap_mm: f64,
    top_of: impl Fn(usize) -> f64,
) -> Option<usize> {
    (0..=below)
        .rev()
        .find(|&k| top_of(k) <= bottom_mm - top_gap_mm + Z_EPS_MM)
}

/// Whether a layer `height_mm` above the bed is held by the bed itself, as by a
/// column's top, with a top gap of `top_gap_mm` (no column fits under it).
pub fn held_by_bed(height_mm: f64, top_gap_mm: f64) -> bool {
    top_gap_mm > 0.0 && height_mm <= top_gap_mm + Z_EPS_MM
}

/// What layer `j` of `stack` rests on: the layer below and the support holding it
/// (`areas`, the stack's supports; `top_gap_mm` under the part); none on the bed (the
/// first layer, or one within the top gap of the bed).
pub fn below_with_support(
    stack: &[StackLayer],
    areas: &[SupportArea],
    j: usize,
    top_gap_mm: f64,
) -> Option<Shapes> {
    let below = j.checked_sub(1)?;
    if held_by_bed(stack[j].bottom_mm() - stack[0].bottom_mm(), top_gap_mm) {
        return None;
    }
    let mut resting = shapes_of(stack[below].islands);
    let hold = holding_layer(below, stack[j].bottom_mm(), top_gap_mm, |k| stack[k].z_mm);
    if let Some(area) = hold.and_then(|k| areas.get(k)).filter(|a| !a.is_empty()) {
        resting = union_into(resting, &area.all());
    }
    Some(resting)
}

/// Each layer's area resting on nothing once `areas` are built under it (layer 0
/// rests on the bed), in parallel, within what rests on nothing without them
/// (`overhangs`, one per layer): support only adds to what a layer rests on, so what
/// hangs with it lies within what hangs without it. Taken within by construction,
/// because the two are found from different outlines (the layer below, or its union
/// with the support), whose offsets differ by µm; where a strip is as wide as the
/// narrowest overhang counted, that flips it between counted and not.
pub fn unsupported_with_support(
    stack: &[StackLayer],
    areas: &[SupportArea],
    overhangs: &[Shapes],
    top_gap_mm: f64,
    opts: &OverhangOptions,
) -> Vec<Shapes> {
    use rayon::prelude::*;
    (0..stack.len())
        .into_par_iter()
        .map(|j| {
            let without = overhangs.get(j).filter(|o| !o.is_empty());
            match (without, below_with_support(stack, areas, j, top_gap_mm)) {
                // Nothing hangs without support, or the layer is on the bed (the
                // first layer, or within the top gap of it).
                (None, _) | (_, None) => Vec::new(),
                (Some(without), Some(below)) => {
                    let with = hanging(stack[j].islands, &below, stack[j].thickness_mm, opts);
                    let mut within = crate::geom::intersection(&with, without);
                    retain_area_at_least(&mut within, opts.min_area_mm2);
                    within
                }
            }
        })
        .collect()
}

/// An overhang waiting, from the top down, for the layer its column starts in.
struct Pending {
    /// The column's top may be no higher than this, mm.
    top_mm: f64,
    area: Shapes,
}

/// Step 3: the support of every layer of `stack` (bottom to top), top down, under
/// each layer's `overhangs` (step 1, one per layer).
pub fn support_areas(
    stack: &[StackLayer],
    overhangs: &[Shapes],
    opts: &SupportAreaOptions,
) -> Vec<SupportArea> {
    let mut out = vec![SupportArea::default(); stack.len()];
    if opts.mode == SupportMode::Off || stack.is_empty() || overhangs.len() != stack.len() {
        return out;
    }
    if overhangs.iter().all(Vec::is_empty) {
        return out;
    }
    let shadows = match opts.mode {
        SupportMode::Buildplate => Some(part_shadows(stack)),
        _ => None,
    };
    let mut pending: Vec<Pending> = Vec::new();
    let mut columns: Shapes = Vec::new();
    // Overhangs released into the columns, with the layer they were released at: the
    // interface is what lies under one released in the last `interface_layers`.
    let mut released: Vec<(usize, Shapes)> = Vec::new();
    for i in (0..stack.len()).rev() {
        let layer = &stack[i];
        let (now, later): (Vec<Pending>, Vec<Pending>) = pending
            .into_iter()
            .partition(|p| layer.z_mm <= p.top_mm + Z_EPS_MM);
        pending = later;
        for p in now {
            columns = union_into(columns, &p.area);
            released.push((i, p.area));
        }
        released.retain(|(at, _)| at - i < opts.interface_layers.max(1));
        let part = shapes_of(layer.islands);
        if !part.is_empty() && !columns.is_empty() {
            columns = without_slivers(difference(&columns, &part), opts);
        }
        if let Some(shadows) = &shadows {
            if !shadows[i].is_empty() && !columns.is_empty() {
                columns = without_slivers(difference(&columns, &shadows[i]), opts);
            }
        }
        if !columns.is_empty() {
            out[i] = layer_support(stack, i, &columns, &released, opts);
        }
        if !overhangs[i].is_empty() {
            let area = if opts.expansion_mm > 0.0 {
                offset(&overhangs[i], opts.expansion_mm, opts.overhang.chord_mm)
            } else {
                overhangs[i].clone()
            };
            pending.push(Pending {
                top_mm: layer.bottom_mm() - opts.top_gap_mm,
                area,
            });
        }
    }
    out
}

/// `shapes` less the pieces a boolean leaves along shared edges: those under a
/// quarter of the narrowest support's square (they would break the offsets of what is
/// built from them, and hold nothing up).
fn without_slivers(mut shapes: Shapes, opts: &SupportAreaOptions) -> Shapes {
    retain_area_at_least(
        &mut shapes,
        (opts.min_width_mm * opts.min_width_mm / 4.0).max(1e-6),
    );
    shapes
}

/// `a` ∪ `b`, without the overlay when one is empty.
fn union_into(a: Shapes, b: &Shapes) -> Shapes {
    if a.is_empty() {
        b.clone()
    } else if b.is_empty() {
        a
    } else {
        union(&a, b)
    }
}

/// Layer `i`'s support: the columns kept clear of the part by the XY gap and off the
/// part below by the bottom gap, narrow strips left out, split into interface and base.
fn layer_support(
    stack: &[StackLayer],
    i: usize,
    columns: &Shapes,
    released: &[(usize, Shapes)],
    opts: &SupportAreaOptions,
) -> SupportArea {
    let chord = opts.overhang.chord_mm;
    let mut keep_out = shapes_of(stack[i].islands);
    if opts.xy_gap_mm > 0.0 && !keep_out.is_empty() {
        keep_out = offset(&keep_out, opts.xy_gap_mm, chord);
    }
    if opts.mode == SupportMode::Everywhere && opts.bottom_gap_mm > 0.0 {
        let floor = stack[i].bottom_mm() - opts.bottom_gap_mm;
        for below in stack[..i].iter().rev() {
            if below.z_mm <= floor + Z_EPS_MM {
                break;
            }
            keep_out = union_into(keep_out, &shapes_of(below.islands));
        }
    }
    let mut support = if keep_out.is_empty() {
        columns.clone()
    } else {
        difference(columns, &keep_out)
    };
    if support.is_empty() {
        return SupportArea::default();
    }
    let half = opts.min_width_mm / 2.0;
    if half > 0.0 {
        let opened = offset(&offset(&support, -half, chord), half, chord);
        support = intersection(&opened, &support);
    }
    let support = without_slivers(support, opts);
    if support.is_empty() {
        return SupportArea::default();
    }
    let under: Shapes = released
        .iter()
        .fold(Vec::new(), |acc, (_, area)| union_into(acc, area));
    if under.is_empty() {
        return SupportArea {
            base: support,
            interface: Vec::new(),
        };
    }
    let interface = without_slivers(intersection(&support, &under), opts);
    let base = if interface.is_empty() {
        support
    } else {
        without_slivers(difference(&support, &interface), opts)
    };
    SupportArea { base, interface }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::area;
    use crate::slice::overhang::Overhang;
    use glam::DVec2;

    fn rect(x0: f64, y0: f64, x1: f64, y1: f64) -> Region {
        Region::new(
            vec![
                DVec2::new(x0, y0),
                DVec2::new(x1, y0),
                DVec2::new(x1, y1),
                DVec2::new(x0, y1),
            ],
            vec![],
        )
    }

    fn opts(mode: SupportMode) -> SupportAreaOptions {
        SupportAreaOptions {
            mode,
            top_gap_mm: 0.0,
            bottom_gap_mm: 0.0,
            xy_gap_mm: 0.2,
            interface_layers: 2,
            overhang: OverhangOptions {
                overhang: Overhang::default(),
                min_width_mm: 0.1,
                min_area_mm2: 0.16,
                chord_mm: 0.005,
            },
            min_width_mm: 0.2,
            expansion_mm: 0.0,
        }
    }

    /// A T: a 2 x 2 mm post 10 layers tall, then a 10 x 2 mm bar on it.
    fn tee() -> Vec<Vec<Region>> {
        let mut layers = vec![vec![rect(4.0, 0.0, 6.0, 2.0)]; 10];
        layers.extend(vec![vec![rect(0.0, 0.0, 10.0, 2.0)]; 3]);
        layers
    }

    fn overhangs_of_stack(stack: &[StackLayer], opts: &OverhangOptions) -> Vec<Shapes> {
        (0..stack.len())
            .map(|k| {
                let below = k.checked_sub(1).map(|j| stack[j].islands);
                crate::slice::overhang::unsupported(
                    stack[k].islands,
                    below,
                    stack[k].thickness_mm,
                    opts,
                )
            })
            .collect()
    }

    /// [`support_areas`] under the stack's own overhangs.
    fn built(stack: &[StackLayer], opts: &SupportAreaOptions) -> Vec<SupportArea> {
        support_areas(stack, &overhangs_of_stack(stack, &opts.overhang), opts)
    }

    fn stack(islands: &[Vec<Region>]) -> Vec<StackLayer<'_>> {
        islands
            .iter()
            .enumerate()
            .map(|(k, i)| StackLayer {
                z_mm: 0.2 * (k + 1) as f64,
                thickness_mm: 0.2,
                islands: i,
            })
            .collect()
    }

    #[test]
    fn a_tee_is_held_under_both_arms_down_to_the_bed() {
        let islands = tee();
        let s = stack(&islands);
        let areas = built(&s, &opts(SupportMode::Buildplate));
        // Under each arm: 4 mm less the XY gap by 2 mm, every layer of the post.
        for (k, a) in areas.iter().enumerate().take(10) {
            let got = area(&a.all()).abs();
            assert!((got - 2.0 * 3.8 * 2.0).abs() < 0.1, "layer {k}: {got}");
        }
        // The top two are interface, the rest base.
        assert!(area(&areas[9].interface).abs() > 15.0);
        assert!(area(&areas[8].interface).abs() > 15.0);
        assert!(areas[7].interface.is_empty());
        assert!(areas[10..].iter().all(SupportArea::is_empty));
        // Off: nothing.
        let none = built(&s, &opts(SupportMode::Off));
        assert!(none.iter().all(SupportArea::is_empty));
    }

    /// A bar over a shelf: the left arm hangs over a lower shelf of the part, the
    /// right one over the bed.
    fn shelf() -> Vec<Vec<Region>> {
        let mut layers = vec![vec![rect(0.0, 0.0, 6.0, 2.0)]; 3];
        layers.extend(vec![vec![rect(4.0, 0.0, 6.0, 2.0)]; 5]);
        layers.extend(vec![vec![rect(0.0, 0.0, 10.0, 2.0)]; 2]);
        layers
    }

    #[test]
    fn everywhere_stands_on_the_part_and_buildplate_does_not() {
        let islands = shelf();
        let s = stack(&islands);
        let everywhere = built(&s, &opts(SupportMode::Everywhere));
        let plate = built(&s, &opts(SupportMode::Buildplate));
        // Above the shelf (layers 3-7): both arms held everywhere, the right only on
        // the build plate.
        for k in 3..8 {
            let e = area(&everywhere[k].all()).abs();
            let p = area(&plate[k].all()).abs();
            assert!((e - 2.0 * 3.8 * 2.0).abs() < 0.1, "layer {k}: {e}");
            assert!((p - 3.8 * 2.0).abs() < 0.1, "layer {k}: {p}");
        }
        // Beside the shelf (layers 0-2) only the right arm's column, both ways.
        for (k, a) in everywhere.iter().enumerate().take(3) {
            let e = area(&a.all()).abs();
            assert!((e - 3.8 * 2.0).abs() < 0.1, "layer {k}: {e}");
        }
        // A bottom gap of one layer keeps the column off the shelf's top.
        let gapped = built(
            &s,
            &SupportAreaOptions {
                bottom_gap_mm: 0.2,
                ..opts(SupportMode::Everywhere)
            },
        );
        let e = area(&gapped[3].all()).abs();
        assert!((e - 3.8 * 2.0).abs() < 0.1, "{e}");
        let e = area(&gapped[4].all()).abs();
        assert!((e - 2.0 * 3.8 * 2.0).abs() < 0.1, "{e}");
    }

    #[test]
    fn nothing_hangs_once_supports_are_built() {
        let islands = shelf();
        let s = stack(&islands);
        let o = opts(SupportMode::Everywhere);
        let before = overhangs_of_stack(&s, &o.overhang);
        assert!(area(&before[8]).abs() > 10.0);
        let areas = built(&s, &o);
        let after = unsupported_with_support(&s, &areas, &before, 0.0, &o.overhang);
        assert!(after.iter().all(Vec::is_empty), "{after:?}");
        // On the build plate only the left arm still hangs.
        let plate = built(&s, &opts(SupportMode::Buildplate));
        let after = unsupported_with_support(&s, &plate, &before, 0.0, &o.overhang);
        let a = area(&after[8]).abs();
        assert!((a - 4.0 * 2.0).abs() < 0.5, "{a}");
    }

    #[test]
    fn a_top_gap_leaves_layers_between_column_and_part() {
        let islands = tee();
        let s = stack(&islands);
        let gapped = built(
            &s,
            &SupportAreaOptions {
                top_gap_mm: 0.2,
                ..opts(SupportMode::Buildplate)
            },
        );
        assert!(gapped[9].is_empty());
        assert!(area(&gapped[8].interface).abs() > 15.0);
    }
}
