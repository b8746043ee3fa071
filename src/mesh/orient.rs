//! Which way up a mesh part is built (`[geometry] orientation`).
//!
//! Step 1 ([`candidates`]): the directions of the part that may go down: the way it
//! was drawn, and the normals of its largest flat faces (faces grouped by normal, the
//! groups with the most area). Step 2 ([`score`]): for each, the part turned so that
//! direction points down (-Z) and measured: the support it would need (each face
//! leaning past the allowed overhang, its area projected on the bed times its height
//! above the bed) and the area it rests on. Step 3 ([`choose`]): the least support; of
//! equal support the most area on the bed, then the lowest part. The report says which
//! was chosen, why, and the runner-up.

use glam::{DQuat, DVec3};
use serde::Serialize;

use super::Mesh;

/// `[geometry] orientation`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Orientation {
    /// As drawn (default).
    #[default]
    Keep,
    /// The candidate that needs the least support ([`choose`]).
    Auto,
    /// Turned about the fixed X, then Y, then Z axes, degrees.
    Rotate([f64; 3]),
}

/// The default allowed overhang: 30 degrees from vertical (a wall may lean out by
/// tan 30 deg = 0.58 of a layer's thickness per layer, so each bead rests on at least
/// about 70 % of its width on the bead below at a layer of half the road). Plastic
/// slicers allow 45 to 55 degrees; a paste has no cooling to set it and slumps. The
/// orientation is chosen by it, and `slice::overhang` measures layers by it.
pub const DEFAULT_OVERHANG_ANGLE_DEG: f64 = 30.0;

/// What scoring a candidate needs.
#[derive(Debug, Clone, Copy)]
pub struct OrientOptions {
    /// The steepest allowed lean from vertical, degrees (`[process] overhang`): faces
    /// leaning further need support.
    pub overhang_angle_deg: f64,
    /// Within this of the bed a face rests on it, mm (half a layer).
    pub on_bed_mm: f64,
    /// Flat-face directions tried besides the part as drawn.
    pub max_candidates: usize,
    /// Support volumes within this fraction of each other are equal.
    pub tie_fraction: f64,
}

impl Default for OrientOptions {
    fn default() -> Self {
        OrientOptions {
            overhang_angle_deg: DEFAULT_OVERHANG_ANGLE_DEG,
            on_bed_mm: 0.1,
            max_candidates: 12,
            tie_fraction: 0.01,
        }
    }
}

/// One way up, measured.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Candidate {
    /// The part's direction (as drawn) that points down.
    pub down: [f64; 3],
    /// The turn, as `orientation = { rotate = [x, y, z] }` would give it, degrees.
    pub rotate_deg: [f64; 3],
    /// Faces leaning past the allowed overhang: their area on the bed times their
    /// height above it, mm³.
    pub support_volume_mm3: f64,
    /// Area of the faces resting on the bed, mm².
    pub bed_contact_mm2: f64,
    /// Height of the part so turned, mm.
    pub height_mm: f64,
}

/// What orienting did (`orientation` in the plan report).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OrientationReport {
    /// `keep`, `auto` or `rotate`.
    pub mode: &'static str,
    pub chosen: Candidate,
    /// Auto: the best of the others.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub runner_up: Option<Candidate>,
    /// Candidates measured.
    pub tried: usize,
    pub why: String,
}

/// The turn that points `down` to -Z, and how [`Orientation::Rotate`] writes it.
pub fn turn_down(down: DVec3) -> DQuat {
    DQuat::from_rotation_arc(down.normalize(), DVec3::NEG_Z)
}

/// The turn of `rotate = [x, y, z]` (degrees about the fixed X, then Y, then Z).
pub fn turn_of(rotate_deg: [f64; 3]) -> DQuat {
    let [x, y, z] = rotate_deg.map(f64::to_radians);
    DQuat::from_rotation_z(z) * DQuat::from_rotation_y(y) * DQuat::from_rotation_x(x)
}

/// `q` as `rotate = [x, y, z]` degrees.
pub fn rotate_deg_of(q: DQuat) -> [f64; 3] {
    let (z, y, x) = q.to_euler(glam::EulerRot::ZYX);
    [x, y, z].map(|a| {
        let d = a.to_degrees();
        // Rounded to 1e-6 degree: 90, not 89.99999999999999.
        (d * 1e6).round() / 1e6 + 0.0
    })
}

/// The directions to try: the part as drawn (-Z), then the normals of its largest
/// flat faces (triangles grouped by normal to 0.01), most area first.
pub fn candidates(mesh: &Mesh, max: usize) -> Vec<DVec3> {
    use std::collections::HashMap;
    let mut by_normal: HashMap<[i64; 3], (DVec3, f64)> = HashMap::new();
    for t in &mesh.triangles {
        let Some([a, b, c]) = corners(&mesh.vertices, t) else {
            continue;
        };
        let n = (b - a).cross(c - a);
        let len = n.length();
        if len <= 0.0 || !len.is_finite() {
            continue;
        }
        let unit = n / len;
        let key = (unit * 100.0).round().as_i64vec3().to_array();
        let e = by_normal.entry(key).or_insert((DVec3::ZERO, 0.0));
        e.0 += n;
        e.1 += len / 2.0;
    }
    let mut groups: Vec<(DVec3, f64)> = by_normal.into_values().collect();
    groups.sort_by(|a, b| b.1.total_cmp(&a.1));
    let mut out = vec![DVec3::NEG_Z];
    for (n, _) in groups {
        let d = n.normalize_or_zero();
        if d == DVec3::ZERO || out.iter().any(|o| o.dot(d) > 0.9999) {
            continue;
        }
        out.push(d);
        if out.len() > max {
            break;
        }
    }
    out
}

/// A triangle's corners among `vertices` (none for an index out of range).
fn corners(vertices: &[DVec3], t: &[u32; 3]) -> Option<[DVec3; 3]> {
    let v = |i: u32| vertices.get(i as usize).copied();
    Some([v(t[0])?, v(t[1])?, v(t[2])?])
}

/// `mesh` turned so `down` points down, measured.
pub fn score(mesh: &Mesh, down: DVec3, opts: &OrientOptions) -> Candidate {
    let q = turn_down(down);
    let turned: Vec<DVec3> = mesh.vertices.iter().map(|&v| q * v).collect();
    let (lo, hi) = turned
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v.z), hi.max(v.z))
        });
    let leaning = opts.overhang_angle_deg.to_radians().sin();
    let (mut support, mut contact) = (0.0, 0.0);
    for t in &mesh.triangles {
        let Some([a, b, c]) = corners(&turned, t) else {
            continue;
        };
        let n = (b - a).cross(c - a);
        let len = n.length();
        if len <= 0.0 || !len.is_finite() {
            continue;
        }
        let (area, nz) = (len / 2.0, n.z / len);
        let top = a.z.max(b.z).max(c.z) - lo;
        if top <= opts.on_bed_mm {
            if nz < 0.0 {
                contact += area * -nz;
            }
            continue;
        }
        if -nz > leaning {
            let height = (a.z + b.z + c.z) / 3.0 - lo;
            support += area * -nz * height;
        }
    }
    Candidate {
        down: down.to_array(),
        rotate_deg: rotate_deg_of(q),
        support_volume_mm3: support,
        bed_contact_mm2: contact,
        height_mm: if hi >= lo { hi - lo } else { 0.0 },
    }
}

/// Whether `a` is a better way up than `b`: less support (beyond `tie`), then more
/// area on the bed, then lower.
fn better(a: &Candidate, b: &Candidate, tie: f64) -> bool {
    let margin = tie * a.support_volume_mm3.max(b.support_volume_mm3) + 1e-6;
    if (a.support_volume_mm3 - b.support_volume_mm3).abs() > margin {
        return a.support_volume_mm3 < b.support_volume_mm3;
    }
    if (a.bed_contact_mm2 - b.bed_contact_mm2).abs() > 1e-6 {
        return a.bed_contact_mm2 > b.bed_contact_mm2;
    }
    a.height_mm < b.height_mm
}

/// The way up `orientation` asks for, measured; `keep_z`: the design varies along Z,
/// so auto keeps the part as drawn (its Z stations stay along the build direction).
pub fn choose(
    mesh: &Mesh,
    orientation: Orientation,
    keep_z: bool,
    opts: &OrientOptions,
) -> (DQuat, OrientationReport) {
    match orientation {
        Orientation::Keep => (
            DQuat::IDENTITY,
            only(
                "keep",
                score(mesh, DVec3::NEG_Z, opts),
                "as drawn ([geometry] orientation = \"keep\")".into(),
            ),
        ),
        Orientation::Rotate(r) => {
            let q = turn_of(r);
            // Support, contact and height do not change with a turn about Z.
            let c = score(mesh, q.inverse() * DVec3::NEG_Z, opts);
            let why = format!("turned as asked (rotate = {r:?} degrees about X, Y, Z)");
            (q, only("rotate", Candidate { rotate_deg: r, ..c }, why))
        }
        Orientation::Auto if keep_z => (
            DQuat::IDENTITY,
            only(
                "auto",
                score(mesh, DVec3::NEG_Z, opts),
                "as drawn: the gradient varies along Z, and its stations stay along the \
                 build direction only so"
                    .into(),
            ),
        ),
        Orientation::Auto => auto(mesh, opts),
    }
}

/// The report of a way up that was the only one measured.
fn only(mode: &'static str, chosen: Candidate, why: String) -> OrientationReport {
    OrientationReport {
        mode,
        chosen,
        runner_up: None,
        tried: 1,
        why,
    }
}

/// [`Orientation::Auto`]: every candidate measured, the best chosen.
fn auto(mesh: &Mesh, opts: &OrientOptions) -> (DQuat, OrientationReport) {
    let mut scored: Vec<Candidate> = candidates(mesh, opts.max_candidates)
        .into_iter()
        .map(|d| score(mesh, d, opts))
        .collect();
    let tried = scored.len();
    let mut best = 0;
    for k in 1..scored.len() {
        if better(&scored[k], &scored[best], opts.tie_fraction) {
            best = k;
        }
    }
    let chosen = scored.swap_remove(best);
    let mut runner_up: Option<Candidate> = None;
    for c in scored {
        if runner_up.is_none_or(|r| better(&c, &r, opts.tie_fraction)) {
            runner_up = Some(c);
        }
    }
    let why = match &runner_up {
        Some(r)
            if (chosen.support_volume_mm3 - r.support_volume_mm3).abs()
                > opts.tie_fraction * r.support_volume_mm3 + 1e-6 =>
        {
            format!(
                "the least support: {:.0} mm³ against {:.0} mm³ for the runner-up",
                chosen.support_volume_mm3, r.support_volume_mm3
            )
        }
        Some(r) => format!(
            "support as little as the runner-up's ({:.0} mm³), and the most on the bed: \
             {:.0} mm² against {:.0} mm²",
            chosen.support_volume_mm3, chosen.bed_contact_mm2, r.bed_contact_mm2
        ),
        None => "the only candidate".into(),
    };
    let q = turn_down(DVec3::from_array(chosen.down));
    let report = OrientationReport {
        mode: "auto",
        chosen,
        runner_up,
        tried,
        why,
    };
    (q, report)
}

/// Turn every vertex of `mesh` by `q`.
pub fn turn(mesh: &mut Mesh, q: DQuat) {
    if q == DQuat::IDENTITY {
        return;
    }
    for v in &mut mesh.vertices {
        *v = q * *v;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An L-bracket lying on its side: legs 40 and 30 mm, 5 mm wide, 20 mm thick.
    fn l_bracket_on_its_side() -> Mesh {
        crate::mesh::primitives::l_bracket(40.0, 30.0, 5.0, 20.0)
    }

    #[test]
    fn auto_puts_an_l_brackets_largest_face_down() {
        let mesh = l_bracket_on_its_side();
        let (q, report) = choose(&mesh, Orientation::Auto, false, &OrientOptions::default());
        // The 40 x 20 mm face of the long leg (its normal -Y) goes on the bed.
        let down = DVec3::from_array(report.chosen.down);
        assert!(down.dot(DVec3::NEG_Y) > 0.999, "{report:?}");
        assert!(
            (report.chosen.bed_contact_mm2 - 800.0).abs() < 1e-6,
            "{report:?}"
        );
        assert_eq!(report.chosen.support_volume_mm3, 0.0);
        let r = report.runner_up.unwrap();
        assert!(r.bed_contact_mm2 < 800.0, "{r:?}");
        assert!(report.why.contains("the most on the bed"), "{}", report.why);
        // The turn puts it there, and rotate = [..] says the same turn.
        let turned = q * DVec3::NEG_Y;
        assert!(turned.dot(DVec3::NEG_Z) > 0.999);
        let again = turn_of(report.chosen.rotate_deg);
        assert!(
            (again * DVec3::NEG_Y).dot(DVec3::NEG_Z) > 0.999,
            "{:?}",
            report.chosen
        );
    }

    #[test]
    fn auto_turns_a_part_off_its_overhang() {
        // The bracket stood on the end of its short leg: the long leg hangs out 35 mm
        // at 30 mm; any flat face down needs less.
        let mut mesh = l_bracket_on_its_side();
        turn(&mut mesh, turn_down(DVec3::Y));
        let kept = score(&mesh, DVec3::NEG_Z, &OrientOptions::default());
        assert!(kept.support_volume_mm3 > 1000.0, "{kept:?}");
        let (_, report) = choose(&mesh, Orientation::Auto, false, &OrientOptions::default());
        assert!(report.chosen.support_volume_mm3 < kept.support_volume_mm3);
        assert!(report.why.contains("support"), "{}", report.why);
        // A Z-varying design keeps it as drawn.
        let (q, report) = choose(&mesh, Orientation::Auto, true, &OrientOptions::default());
        assert_eq!(q, DQuat::IDENTITY);
        assert!(report.why.contains("along Z"), "{}", report.why);
    }

    #[test]
    fn rotate_angles_round_trip() {
        for r in [
            [90.0, 0.0, 0.0],
            [0.0, -90.0, 0.0],
            [30.0, 20.0, 10.0],
            [0.0, 0.0, 45.0],
        ] {
            let back = rotate_deg_of(turn_of(r));
            for k in 0..3 {
                assert!((back[k] - r[k]).abs() < 1e-6, "{r:?} -> {back:?}");
            }
        }
    }
}
