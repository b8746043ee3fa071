//! Beads from G-code: every extrusion of an RRF-flavour file (`E` words `a:b:c`,
//! relative, `;LAYER:`, `;TYPE:`) laid on a raster per layer, and the layers whose
//! part beads rest on nothing beyond the allowed overhang. Shared by
//! `tests/supports.rs` and `examples/gcode_overhangs.rs` (which checks another
//! slicer's G-code the same way, for `benches/supports_vs_prusaslicer.sh`).

#![allow(dead_code)]

use std::collections::BTreeMap;

/// One extrusion of the file: from, to, bead width (mm), and whether it builds support.
pub struct Bead {
    pub from: [f64; 2],
    pub to: [f64; 2],
    pub width_mm: f64,
    pub support: bool,
    /// Volume per drive, mm of plunger.
    pub drives: Vec<f64>,
}

/// The layers of an RRF-flavour file (`E` words `a:b:c`, relative), with their
/// thickness: each layer's beads.
pub struct Layers {
    pub layers: BTreeMap<usize, (f64, Vec<Bead>)>,
}

pub fn parse_gcode(text: &str) -> Layers {
    let barrel_mm2: f64 = text
        .lines()
        .find_map(|l| l.split("barrel area ").nth(1))
        .and_then(|s| s.split_whitespace().next())
        .and_then(|s| s.parse().ok())
        .expect("the header names the barrel area");
    let mut layers = BTreeMap::new();
    let (mut layer, mut z) = (None::<usize>, 0.0);
    let mut at = [0.0f64; 2];
    let mut support = false;
    for line in text.lines() {
        if let Some(rest) = line.strip_prefix(";LAYER:") {
            let mut it = rest.split_whitespace();
            let n: usize = it.next().unwrap().parse().unwrap();
            let new_z: f64 = it.next().unwrap()[1..].parse().unwrap();
            let below_z = if layer.is_some() { z } else { 0.0 };
            z = new_z;
            layer = Some(n);
            layers.insert(n, (z - below_z, Vec::new()));
            continue;
        }
        if let Some(t) = line.strip_prefix(";TYPE:") {
            support = t.starts_with("Support");
            continue;
        }
        let code = line.split(';').next().unwrap_or("");
        let mut words = code.split_whitespace();
        let g = words.next();
        if g != Some("G1") && g != Some("G0") {
            continue;
        }
        let mut to = at;
        let mut e: Option<Vec<f64>> = None;
        for w in words {
            match w.as_bytes()[0] {
                b'X' => to[0] = w[1..].parse().unwrap(),
                b'Y' => to[1] = w[1..].parse().unwrap(),
                b'E' => e = Some(w[1..].split(':').map(|v| v.parse().unwrap()).collect()),
                _ => {}
            }
        }
        let moved = ((to[0] - at[0]).powi(2) + (to[1] - at[1]).powi(2)).sqrt();
        if let (Some(e), Some(n)) = (e, layer) {
            let total: f64 = e.iter().sum();
            if total > 0.0 && moved > 1e-6 {
                let (thickness, beads) = layers.get_mut(&n).unwrap();
                let volume_mm3 = total * barrel_mm2;
                let width_mm = (volume_mm3 / (moved * *thickness)).clamp(0.05, 1.5);
                beads.push(Bead {
                    from: at,
                    to,
                    width_mm,
                    support,
                    drives: e,
                });
            }
        }
        at = to;
    }
    Layers { layers }
}

/// A raster of one layer's beads.
pub struct Raster {
    origin: [f64; 2],
    cell_mm: f64,
    nx: usize,
    ny: usize,
    cells: Vec<bool>,
}

impl Raster {
    pub fn new(lo: [f64; 2], hi: [f64; 2], cell_mm: f64) -> Self {
        let nx = ((hi[0] - lo[0]) / cell_mm).ceil() as usize + 1;
        let ny = ((hi[1] - lo[1]) / cell_mm).ceil() as usize + 1;
        Raster {
            origin: lo,
            cell_mm,
            nx,
            ny,
            cells: vec![false; nx * ny],
        }
    }

    pub fn centre(&self, i: usize, j: usize) -> [f64; 2] {
        [
            self.origin[0] + (i as f64 + 0.5) * self.cell_mm,
            self.origin[1] + (j as f64 + 0.5) * self.cell_mm,
        ]
    }

    /// Mark the cells whose centre is within `r` of segment a-b.
    pub fn stroke(&mut self, a: [f64; 2], b: [f64; 2], r: f64) {
        let c = self.cell_mm;
        let lo = [a[0].min(b[0]) - r, a[1].min(b[1]) - r];
        let hi = [a[0].max(b[0]) + r, a[1].max(b[1]) + r];
        let i0 = (((lo[0] - self.origin[0]) / c).floor().max(0.0)) as usize;
        let j0 = (((lo[1] - self.origin[1]) / c).floor().max(0.0)) as usize;
        let i1 = (((hi[0] - self.origin[0]) / c).ceil() as usize).min(self.nx - 1);
        let j1 = (((hi[1] - self.origin[1]) / c).ceil() as usize).min(self.ny - 1);
        let d = [b[0] - a[0], b[1] - a[1]];
        let len2 = d[0] * d[0] + d[1] * d[1];
        for j in j0..=j1 {
            for i in i0..=i1 {
                let p = self.centre(i, j);
                let t = if len2 > 0.0 {
                    (((p[0] - a[0]) * d[0] + (p[1] - a[1]) * d[1]) / len2).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let q = [a[0] + t * d[0] - p[0], a[1] + t * d[1] - p[1]];
                if q[0] * q[0] + q[1] * q[1] <= r * r {
                    self.cells[j * self.nx + i] = true;
                }
            }
        }
    }

    /// The same grid with `cells` marked.
    pub fn with_cells(&self, cells: Vec<bool>) -> Raster {
        assert_eq!(cells.len(), self.cells.len());
        Raster { cells, ..*self }
    }

    /// The cells not marked.
    pub fn inverted(&self) -> Raster {
        self.with_cells(self.cells.iter().map(|c| !c).collect())
    }

    /// The cells within `r` of a marked one (exact Euclidean distance on cell
    /// centres, by Felzenszwalb and Huttenlocher's distance transform).
    pub fn grown(&self, r: f64) -> Raster {
        let d2 = squared_distances(&self.cells, self.nx, self.ny);
        let k = r / self.cell_mm;
        self.with_cells(d2.iter().map(|d| *d <= k * k + 1e-9).collect())
    }
}

/// Squared distance, in cells, from each cell to the nearest marked one.
pub fn squared_distances(cells: &[bool], nx: usize, ny: usize) -> Vec<f64> {
    const FAR: f64 = 1e20;
    let mut d: Vec<f64> = cells.iter().map(|c| if *c { 0.0 } else { FAR }).collect();
    let mut line = Vec::new();
    let mut out = Vec::new();
    for j in 0..ny {
        line.clear();
        line.extend_from_slice(&d[j * nx..(j + 1) * nx]);
        transform_1d(&line, &mut out);
        d[j * nx..(j + 1) * nx].copy_from_slice(&out);
    }
    for i in 0..nx {
        line.clear();
        line.extend((0..ny).map(|j| d[j * nx + i]));
        transform_1d(&line, &mut out);
        for j in 0..ny {
            d[j * nx + i] = out[j];
        }
    }
    d
}

/// The 1-D squared distance transform of sampled function `f` (lower envelope of
/// parabolas).
pub fn transform_1d(f: &[f64], out: &mut Vec<f64>) {
    let n = f.len();
    out.clear();
    out.resize(n, 0.0);
    let mut v = vec![0usize; n];
    let mut z = vec![0.0f64; n + 1];
    let mut k = 0usize;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    for q in 1..n {
        loop {
            let p = v[k];
            let s = ((f[q] + (q * q) as f64) - (f[p] + (p * p) as f64)) / (2.0 * (q - p) as f64);
            if s <= z[k] && k > 0 {
                k -= 1;
                continue;
            }
            if s <= z[k] {
                // k == 0 and the new parabola is lower everywhere.
                v[0] = q;
                z[1] = f64::INFINITY;
                break;
            }
            k += 1;
            v[k] = q;
            z[k] = s;
            z[k + 1] = f64::INFINITY;
            break;
        }
    }
    let mut k = 0;
    for (q, o) in out.iter_mut().enumerate() {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let p = v[k];
        *o = (q as f64 - p as f64).powi(2) + f[p];
    }
}

pub fn raster_of(beads: &[&Bead], lo: [f64; 2], hi: [f64; 2], cell: f64) -> Raster {
    let mut r = Raster::new(lo, hi, cell);
    for b in beads {
        r.stroke(b.from, b.to, b.width_mm / 2.0);
    }
    r
}

/// The pieces of `cells` (4-connected): their areas, mm², and a point of each.
pub fn pieces(r: &Raster, cells: &[bool]) -> Vec<(f64, [f64; 2])> {
    let mut seen = vec![false; cells.len()];
    let mut out = Vec::new();
    for start in 0..cells.len() {
        if !cells[start] || seen[start] {
            continue;
        }
        let mut n = 0usize;
        let mut stack = vec![start];
        seen[start] = true;
        while let Some(c) = stack.pop() {
            n += 1;
            let (i, j) = (c % r.nx, c / r.nx);
            let mut push = |x: usize, y: usize| {
                let k = y * r.nx + x;
                if cells[k] && !seen[k] {
                    seen[k] = true;
                    stack.push(k);
                }
            };
            if i > 0 {
                push(i - 1, j);
            }
            if i + 1 < r.nx {
                push(i + 1, j);
            }
            if j > 0 {
                push(i, j - 1);
            }
            if j + 1 < r.ny {
                push(i, j + 1);
            }
        }
        out.push((
            n as f64 * r.cell_mm * r.cell_mm,
            r.centre(start % r.nx, start / r.nx),
        ));
    }
    out
}

/// What the check lets a layer leave resting on nothing: the planner's reach
/// (`t · tan(30°)` past the layer below) and its smallest piece (the nozzle
/// squared), and strips narrower than a quarter of the nozzle (the planner counts
/// down to twice the contour deviation, from outlines; beads run wider than their
/// outline by a few hundredths where the flow is raised).
pub struct Allowance {
    pub nozzle_mm: f64,
}

impl Allowance {
    pub fn reach_mm(&self, thickness_mm: f64) -> f64 {
        thickness_mm * 30f64.to_radians().tan()
    }
    pub fn min_width_mm(&self) -> f64 {
        self.nozzle_mm / 4.0
    }
    pub fn min_area_mm2(&self) -> f64 {
        self.nozzle_mm * self.nozzle_mm
    }
    /// Raster cells a sixteenth of the nozzle.
    pub fn cell_mm(&self) -> f64 {
        self.nozzle_mm / 16.0
    }
}

/// The bounds of `beads`, grown by `margin`.
pub fn bounds_of(beads: &[&Bead], margin: f64) -> ([f64; 2], [f64; 2]) {
    let lo = beads.iter().fold([f64::MAX; 2], |a, b| {
        [
            a[0].min(b.from[0].min(b.to[0])),
            a[1].min(b.from[1].min(b.to[1])),
        ]
    });
    let hi = beads.iter().fold([f64::MIN; 2], |a, b| {
        [
            a[0].max(b.from[0].max(b.to[0])),
            a[1].max(b.from[1].max(b.to[1])),
        ]
    });
    (
        [lo[0] - margin, lo[1] - margin],
        [hi[0] + margin, hi[1] + margin],
    )
}

/// Layers of the file whose part beads reach past the beads below (the part's and
/// the support's) by more than `allowed` lets them: (layer, mm²) of each. What lies
/// below a layer of the part is the last layer with part beads and every support
/// laid since (a slicer may lay support at heights of its own between the part's
/// layers); its thickness is the height above that layer. Each layer is rastered over
/// its own bounds and those of what lies below.
pub fn unsupported_layers(g: &Layers, allowed: &Allowance) -> Vec<(usize, f64)> {
    let cell = allowed.cell_mm();
    let mut out = Vec::new();
    let mut below: Option<Vec<&Bead>> = None;
    let (mut z, mut part_z) = (0.0, 0.0);
    for (&n, (layer_thickness, beads)) in &g.layers {
        z += layer_thickness;
        let part: Vec<&Bead> = beads.iter().filter(|b| !b.support).collect();
        if part.is_empty() {
            // Support alone: under the next layer of the part, with what was below.
            below.get_or_insert_with(Vec::new).extend(beads.iter());
            continue;
        }
        let thickness = &(z - part_z);
        part_z = z;
        if let Some(under) = below.as_ref() {
            let both: Vec<&Bead> = part.iter().chain(under.iter()).copied().collect();
            let (lo, hi) = bounds_of(&both, 2.0);
            let here = raster_of(&part, lo, hi, cell);
            let resting = raster_of(under, lo, hi, cell).grown(allowed.reach_mm(*thickness));
            let hanging: Vec<bool> = here
                .cells
                .iter()
                .zip(&resting.cells)
                .map(|(h, r)| *h && !*r)
                .collect();
            // Strips narrower than the allowed width are not overhangs: an opening.
            let h = here.with_cells(hanging);
            let half = allowed.min_width_mm() / 2.0;
            let eroded = h.inverted().grown(half).inverted();
            let opened = eroded.grown(half);
            let kept: Vec<bool> = opened
                .cells
                .iter()
                .zip(&h.cells)
                .map(|(o, h)| *o && *h)
                .collect();
            let big: Vec<(f64, [f64; 2])> = pieces(&h, &kept)
                .into_iter()
                .filter(|(a, _)| *a > allowed.min_area_mm2())
                .collect();
            if !big.is_empty() {
                // Where, for a person finding out why (machine coordinates).
                eprintln!("layer {n}: resting on nothing: {big:?}");
                out.push((n, big.iter().map(|b| b.0).sum()));
            }
        }
        // What the next layer rests on: this layer's part and support beads.
        below = Some(beads.iter().collect());
    }
    out
}

/// The nozzle (`[process] nozzle`, mm) of job `text`.
pub fn nozzle_of(text: &str) -> f64 {
    text.lines()
        .find_map(|l| l.trim().strip_prefix("nozzle ="))
        .and_then(|v| v.split('#').next())
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no nozzle in {text}"))
}
