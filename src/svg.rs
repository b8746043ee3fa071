//! SVG previews of planned layers (Fig. 3 and 4 of the paper): every road coloured by
//! its composition, contours drawn bolder than equal distance offsets, the part
//! boundary in grey, and a legend mapping colours to materials and showing the
//! contour compositions from Ci to Ce.
//!
//! Pure: returns the SVG text; writing files is the caller's business.

use crate::geom::Path;
use crate::geom::Region;
use crate::plan::{offset_composition_eq6, LayerPlan, RegionPlan};
use glam::DVec2;
use std::fmt::Write;

/// Base colours of up to 8 materials, in syringe order (sRGB).
pub const PALETTE: [[u8; 3]; 8] = [
    [31, 119, 180],
    [214, 39, 40],
    [44, 160, 44],
    [255, 127, 14],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [23, 190, 207],
];

/// The colour of a composition: the fraction-weighted mix of its materials' colours.
pub fn mix_colour(fractions: &[f64]) -> String {
    let mut rgb = [0.0f64; 3];
    for (k, f) in fractions.iter().enumerate() {
        let base = PALETTE[k % PALETTE.len()];
        for c in 0..3 {
            rgb[c] += f.clamp(0.0, 1.0) * base[c] as f64;
        }
    }
    format!(
        "#{:02x}{:02x}{:02x}",
        rgb[0].round().clamp(0.0, 255.0) as u8,
        rgb[1].round().clamp(0.0, 255.0) as u8,
        rgb[2].round().clamp(0.0, 255.0) as u8
    )
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// What to draw around the roads.
pub struct PreviewInput<'a> {
    pub job_name: &'a str,
    pub materials: &'a [String],
    pub nozzle_mm: f64,
    pub islands: &'a [Region],
    /// The layer's area resting on nothing (`slice::overhang`), drawn red over the
    /// roads; empty: nothing drawn.
    pub unsupported: &'a crate::geom::Shapes,
}

struct Frame {
    lo: DVec2,
    hi: DVec2,
}

impl Frame {
    /// The frame around the part and the given points, with a margin of a road width
    /// plus 2 % (the planned and the as-built drawings of a layer get the same frame).
    fn around(
        islands: &[Region],
        points: impl Iterator<Item = DVec2>,
        road_width_mm: f64,
    ) -> Frame {
        let (mut lo, mut hi) = crate::geom::bounds_of(islands);
        for q in points {
            lo = lo.min(q);
            hi = hi.max(q);
        }
        if !lo.is_finite() || !hi.is_finite() {
            lo = DVec2::ZERO;
            hi = DVec2::ONE;
        }
        let margin = road_width_mm + 0.02 * (hi - lo).max_element();
        Frame {
            lo: lo - DVec2::splat(margin),
            hi: hi + DVec2::splat(margin),
        }
    }

    /// The `<svg>` element (1000 px on the long side), its title and the part's outline.
    fn open(&self, out: &mut String, title: &str, islands: &[Region], thin: f64) {
        let size = self.hi - self.lo;
        let px = 1000.0 / size.x.max(size.y).max(1e-9);
        let _ = writeln!(
            out,
            r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {:.3} {:.3}" width="{:.0}" height="{:.0}">"#,
            size.x,
            size.y,
            size.x * px,
            size.y * px
        );
        let _ = writeln!(out, "<title>{}</title>", escape(title));
        for r in islands {
            for l in r.loops() {
                let _ = writeln!(
                    out,
                    r##"<polygon points="{}" fill="none" stroke="#999999" stroke-width="{thin:.3}"/>"##,
                    self.points(l)
                );
            }
        }
    }

    fn xy(&self, p: DVec2) -> (f64, f64) {
        (p.x - self.lo.x, self.hi.y - p.y)
    }

    fn points(&self, pts: &[DVec2]) -> String {
        let mut s = String::with_capacity(pts.len() * 16);
        for p in pts {
            let (x, y) = self.xy(*p);
            let _ = write!(s, "{x:.3},{y:.3} ");
        }
        s
    }
}

fn path_element(out: &mut String, f: &Frame, p: &Path, colour: &str, width: f64, extra: &str) {
    let tag = if p.closed { "polygon" } else { "polyline" };
    let _ = writeln!(
        out,
        r#"<{tag} points="{}" fill="none" stroke="{colour}" stroke-width="{width:.3}" stroke-linejoin="round" stroke-linecap="round"{extra}/>"#,
        f.points(&p.points)
    );
}

/// One layer as an SVG document: the part's boundary, the equal distance offsets under
/// the contours, and the legend to the right of the part.
pub fn layer_svg(layer: &LayerPlan, input: &PreviewInput) -> String {
    let f = Frame::around_part(input.islands, &layer.support);
    let page = LegendPage::new(&f, layer, input);
    let mut out = String::new();
    page.open(&mut out, layer, input);
    boundary_group(&mut out, &f, input);
    road_groups(&mut out, &f, layer, input.nozzle_mm);
    area_group(&mut out, &f, &layer.support.base, SUPPORT_AREA_STYLE);
    area_group(&mut out, &f, &layer.support.interface, INTERFACE_AREA_STYLE);
    area_group(&mut out, &f, input.unsupported, UNSUPPORTED_STYLE);
    page.legend(&mut out, layer, input);
    out
}

/// The colour of area resting on nothing, in every preview.
pub const UNSUPPORTED_COLOUR: &str = "#e0002a";
/// The colour of support (its sparse base), in every preview: no material's.
pub const SUPPORT_COLOUR: &str = "#8c8c8c";
/// The colour of support interface (the dense top of a column), in every preview.
pub const SUPPORT_INTERFACE_COLOUR: &str = "#4d4d4d";

/// How an area is drawn: group id, colour, opacity, title.
type AreaStyle = (&'static str, &'static str, f64, &'static str);
const UNSUPPORTED_STYLE: AreaStyle = (
    "unsupported",
    UNSUPPORTED_COLOUR,
    0.5,
    "area resting on nothing (beyond the allowed overhang)",
);
const SUPPORT_AREA_STYLE: AreaStyle = ("support", SUPPORT_COLOUR, 0.45, "support");
const INTERFACE_AREA_STYLE: AreaStyle = (
    "support-interface",
    SUPPORT_INTERFACE_COLOUR,
    0.45,
    "support interface",
);

/// `shapes` filled in `style`, half transparent, over the roads.
fn area_group(out: &mut String, f: &Frame, shapes: &crate::geom::Shapes, style: AreaStyle) {
    if shapes.is_empty() {
        return;
    }
    let (id, colour, opacity, title) = style;
    let _ = writeln!(
        out,
        r#"<g id="{id}" fill="{colour}" fill-opacity="{opacity}" fill-rule="evenodd" stroke="{colour}" stroke-width="0.02"><title>{title}</title>"#
    );
    for shape in shapes {
        let mut d = String::new();
        for l in shape {
            let _ = write!(d, "M{}Z ", f.points(l).trim_end().replace(' ', " L"));
        }
        let _ = writeln!(out, r#"<path d="{}"/>"#, d.trim_end());
    }
    let _ = writeln!(out, "</g>");
}

/// The colour a road is drawn in: its composition's, or the support's grey.
pub fn road_colour(p: &crate::toolpath::ToolPath) -> String {
    match p.role {
        crate::toolpath::PathRole::Support => SUPPORT_COLOUR.to_string(),
        crate::toolpath::PathRole::SupportInterface => SUPPORT_INTERFACE_COLOUR.to_string(),
        _ => mix_colour(&p.composition),
    }
}

/// Most contours the legend lists (evenly picked from C1..Cm+1).
const LEGEND_CONTOURS: usize = 14;

impl Frame {
    /// The frame around the part and its support with a margin of 5 % of its larger
    /// side (at least 0.05 mm).
    fn around_part(islands: &[Region], support: &crate::slice::support::SupportArea) -> Frame {
        let mut lo = DVec2::splat(f64::INFINITY);
        let mut hi = DVec2::splat(f64::NEG_INFINITY);
        for r in islands {
            let (a, b) = r.bounds();
            lo = lo.min(a);
            hi = hi.max(b);
        }
        let support_loops =
            crate::geom::loops(&support.base).chain(crate::geom::loops(&support.interface));
        for l in support_loops {
            let (a, b) = crate::geom::loop_bounds(l);
            lo = lo.min(a);
            hi = hi.max(b);
        }
        if !lo.is_finite() || !hi.is_finite() {
            lo = DVec2::ZERO;
            hi = DVec2::ONE;
        }
        let margin = 0.05 * (hi - lo).max_element().max(1.0);
        Frame {
            lo: lo - DVec2::splat(margin),
            hi: hi + DVec2::splat(margin),
        }
    }
}

/// The page of a layer preview: the part's frame on the left, the legend on the right.
struct LegendPage {
    /// The part's frame, mm.
    size: DVec2,
    legend_w: f64,
    total_w: f64,
    height: f64,
    /// One legend row, mm.
    line: f64,
}

impl LegendPage {
    fn new(f: &Frame, layer: &LayerPlan, input: &PreviewInput) -> LegendPage {
        let size = f.hi - f.lo;
        let legend_w = size.x.max(size.y) * 0.75;
        let total_w = size.x + legend_w;
        // Legend rows: title, materials, contour header, the contours listed, footer.
        let contour_rows = layer
            .regions
            .first()
            .map_or(0, |r| r.contours.len().min(LEGEND_CONTOURS));
        let rows = 4 + input.materials.len() + contour_rows;
        let line = size.x.max(size.y) / 28.0;
        let height = size.y.max(line * (rows as f64 + 1.0));
        LegendPage {
            size,
            legend_w,
            total_w,
            height,
            line,
        }
    }

    /// The `<svg>` element (1000 px wide), its title and a white background.
    fn open(&self, out: &mut String, layer: &LayerPlan, input: &PreviewInput) {
        let (total_w, height) = (self.total_w, self.height);
        let px_per_mm = 1000.0 / total_w;
        let _ = writeln!(
            out,
            r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {total_w:.3} {height:.3}" width="{:.0}" height="{:.0}">"#,
            total_w * px_per_mm,
            height * px_per_mm
        );
        let _ = writeln!(
            out,
            "<title>{} layer {} z={:.3} mm</title>",
            escape(input.job_name),
            layer.index + 1,
            layer.z_mm
        );
        let _ = writeln!(
            out,
            r#"<rect x="0" y="0" width="{total_w:.3}" height="{:.3}" fill="white"/>"#,
            self.size.y
        );
    }

    /// The legend: job and layer, a swatch per material, the contour compositions
    /// (first region), and the end of the document.
    fn legend(&self, out: &mut String, layer: &LayerPlan, input: &PreviewInput) {
        let line = self.line;
        let x0 = self.size.x + self.legend_w * 0.08;
        let font = line * 0.6;
        let mut y = line;
        let _ = writeln!(
            out,
            r#"<g id="legend" font-family="sans-serif" font-size="{font:.3}">"#
        );
        let _ = writeln!(
            out,
            r#"<text x="{x0:.3}" y="{y:.3}" font-weight="bold">{} — layer {}, z {:.3} mm</text>"#,
            escape(input.job_name),
            // Counted from 1, as edoctl and the dashboard name layers to people (the
            // file is layer-NNNN.svg from 0).
            layer.index + 1,
            layer.z_mm
        );
        y += line;
        for (k, name) in input.materials.iter().enumerate() {
            let mut pure = vec![0.0; input.materials.len()];
            pure[k] = 1.0;
            let _ = writeln!(
                out,
                r#"<rect x="{x0:.3}" y="{:.3}" width="{:.3}" height="{:.3}" fill="{}"/><text x="{:.3}" y="{y:.3}">{}</text>"#,
                y - font,
                font,
                font,
                mix_colour(&pure),
                x0 + font * 1.5,
                escape(name)
            );
            y += line;
        }
        if let Some(r) = layer.regions.first() {
            self.contour_legend(out, r, x0, y);
        }
        let _ = writeln!(out, "</g>\n</svg>");
    }

    /// Up to [`LEGEND_CONTOURS`] contours of `r` with their compositions, from `y`.
    fn contour_legend(&self, out: &mut String, r: &RegionPlan, x0: f64, mut y: f64) {
        let line = self.line;
        let font = line * 0.6;
        let _ = writeln!(
            out,
            r#"<text x="{x0:.3}" y="{y:.3}">contours C1..C{} ({:?}, m = {})</text>"#,
            r.m + 1,
            r.method,
            r.m
        );
        y += line * 0.5;
        let rows = (r.contours.len()).min(LEGEND_CONTOURS);
        let step = (r.contours.len() as f64 / rows as f64).max(1.0);
        let mut k = 0.0;
        while (k as usize) < r.contours.len() {
            let c = &r.contours[k as usize];
            let label: Vec<String> = c
                .composition
                .fractions()
                .iter()
                .map(|v| format!("{v:.3}"))
                .collect();
            let _ = writeln!(
                out,
                r#"<rect x="{x0:.3}" y="{y:.3}" width="{:.3}" height="{:.3}" fill="{}"/><text x="{:.3}" y="{:.3}">C{} [{}]</text>"#,
                font * 2.0,
                line * 0.8,
                mix_colour(c.composition.fractions()),
                x0 + font * 2.5,
                y + font,
                c.j,
                label.join(", ")
            );
            y += line;
            k += step;
        }
        let _ = writeln!(
            out,
            r#"<text x="{x0:.3}" y="{:.3}">bold: contours; thin: equal distance offsets</text>"#,
            y + line * 0.5
        );
    }
}

/// The part's boundary, grey hairlines a tenth of the nozzle wide.
fn boundary_group(out: &mut String, f: &Frame, input: &PreviewInput) {
    let _ = writeln!(out, r#"<g id="boundary">"#);
    let hair = 0.1 * input.nozzle_mm;
    for r in input.islands {
        for l in r.loops() {
            let _ = writeln!(
                out,
                r#"<polygon points="{}" fill="none" stroke="grey" stroke-width="{hair:.3}"/>"#,
                f.points(l)
            );
        }
    }
    let _ = writeln!(out, "</g>");
}

/// The roads coloured by composition: equal distance offsets, thinner, under the
/// contours.
fn road_groups(out: &mut String, f: &Frame, layer: &LayerPlan, nozzle_mm: f64) {
    let _ = writeln!(out, r#"<g id="offsets">"#);
    for r in &layer.regions {
        for s in &r.sub_regions {
            for (k, paths) in s.offsets.iter().enumerate() {
                let colour = mix_colour(offset_composition_eq6(r, s, k as u32 + 1).fractions());
                for p in paths {
                    path_element(out, f, p, &colour, 0.35 * nozzle_mm, "");
                }
            }
        }
    }
    let _ = writeln!(out, "</g>");
    let _ = writeln!(out, r#"<g id="contours">"#);
    for r in &layer.regions {
        for c in &r.contours {
            let colour = mix_colour(c.composition.fractions());
            for p in &c.roads {
                path_element(out, f, p, &colour, 0.7 * nozzle_mm, "");
            }
        }
    }
    let _ = writeln!(out, "</g>");
}

/// What a road preview draws besides the roads.
pub struct RoadsInput<'a> {
    pub title: &'a str,
    /// The part (outlines in grey).
    pub islands: &'a [Region],
    /// Nominal road width, mm (times each vertex's width factor).
    pub road_width_mm: f64,
    /// Centres of void cells (from `toolpath::coverage::measure_with_voids`), drawn red.
    pub voids: &'a [DVec2],
    /// Size of a void cell, mm.
    pub void_cell_mm: f64,
    /// Roads where the design changes faster than the mixing chamber can: an orange
    /// ring at each road's start, titled with the predicted error and the step.
    pub mixer_limited: &'a [crate::pipeline::MixerLimit],
}

/// A layer's built roads (issue 4 preview): each road at its real width (per edge: the
/// mean of its vertices' width factors) in its composition colour, travel moves between
/// paths as thin dashed lines, seams as black dots (hollow where not at a concave corner),
/// voids highlighted in red. Pure: returns the SVG text.
pub fn roads_svg(paths: &[crate::toolpath::ToolPath], input: &RoadsInput) -> String {
    let f = Frame::around(
        input.islands,
        paths.iter().flat_map(|p| p.points.iter().copied()),
        input.road_width_mm,
    );
    let mut out = String::new();
    let thin = input.road_width_mm * 0.1;
    f.open(&mut out, input.title, input.islands, thin);
    // Roads, edge by edge so widths can vary. Each road is one translucent group, so
    // where two roads overlap the colour darkens but the joins inside one road (its
    // pieces' round caps over each other) do not: per-piece opacity drew a dark dot at
    // every vertex of a road whose width steps, which read as blobs on the part.
    for p in paths {
        let colour = road_colour(p);
        out.push_str(r#"<g opacity="0.85">"#);
        out.push('\n');
        let n = p.points.len();
        let edges = if p.closed { n } else { n.saturating_sub(1) };
        let mut k = 0;
        while k < edges {
            // Merge runs of equal width into one polyline.
            let w = 0.5 * (p.width_factors[k] + p.width_factors[(k + 1) % n]);
            let mut run = vec![p.points[k]];
            while k < edges
                && (0.5 * (p.width_factors[k] + p.width_factors[(k + 1) % n]) - w).abs() < 0.01
            {
                run.push(p.points[(k + 1) % n]);
                k += 1;
            }
            path_element(
                &mut out,
                &f,
                &Path {
                    points: run,
                    closed: false,
                },
                &colour,
                input.road_width_mm * w,
                "",
            );
        }
        out.push_str("</g>\n");
    }
    // Travel and seams.
    for w in paths.windows(2) {
        let (a, b) = (f.xy(w[0].end()), f.xy(w[1].points[0]));
        let _ = writeln!(
            out,
            r##"<line x1="{:.3}" y1="{:.3}" x2="{:.3}" y2="{:.3}" stroke="#333333" stroke-width="{thin:.3}" stroke-dasharray="{:.3}"/>"##,
            a.0,
            a.1,
            b.0,
            b.1,
            thin * 4.0
        );
    }
    for p in paths.iter().filter(|p| p.closed) {
        let (x, y) = f.xy(p.points[0]);
        let fill = if p.seam_at_corner { "#000000" } else { "none" };
        let _ = writeln!(
            out,
            r##"<circle cx="{x:.3}" cy="{y:.3}" r="{:.3}" fill="{fill}" stroke="#000000" stroke-width="{:.3}"/>"##,
            input.road_width_mm * 0.3,
            thin * 0.5
        );
    }
    for m in input.mixer_limited {
        let (x, y) = f.xy(DVec2::new(m.at_mm[0], m.at_mm[1]));
        let _ = writeln!(
            out,
            r##"<circle cx="{x:.3}" cy="{y:.3}" r="{:.3}" fill="none" stroke="#ff8000" stroke-width="{:.3}"><title>mixer-limited road {}: exit off the design by {:.3} after a step of {:.3}</title></circle>"##,
            input.road_width_mm * 1.5,
            thin * 2.0,
            m.path,
            m.error,
            m.step
        );
    }
    for v in input.voids {
        let (x, y) = f.xy(*v);
        let c = input.void_cell_mm;
        let _ = writeln!(
            out,
            r##"<rect x="{:.3}" y="{:.3}" width="{c:.3}" height="{c:.3}" fill="#ff0000"/>"##,
            x - 0.5 * c,
            y - 0.5 * c
        );
    }
    out.push_str("</svg>\n");
    out
}

/// A layer as the machine built it (from its recording, [`crate::machine::record`]):
/// every extrusion at the width its volume gives, coloured by the composition that left
/// the nozzle (after the mixing chamber), over the part's outline. Same frame and colours
/// as [`roads_svg`], so the two compare side by side ([`side_by_side`]).
pub fn built_svg(
    roads: &[crate::machine::record::BuiltRoad],
    islands: &[Region],
    road_width_mm: f64,
    title: &str,
) -> String {
    let f = Frame::around(
        islands,
        roads.iter().flat_map(|r| [r.from, r.to]),
        road_width_mm,
    );
    let mut out = String::new();
    f.open(&mut out, title, islands, road_width_mm * 0.1);
    for r in roads {
        let (a, b) = (f.xy(r.from), f.xy(r.to));
        let _ = writeln!(
            out,
            r#"<line x1="{:.3}" y1="{:.3}" x2="{:.3}" y2="{:.3}" stroke="{}" stroke-width="{:.3}" stroke-linecap="round"/>"#,
            a.0,
            a.1,
            b.0,
            b.1,
            mix_colour(&r.composition),
            // Moves that deposit nothing (dry runs) still show, as hairlines.
            r.width_mm.max(road_width_mm * 0.1)
        );
    }
    out.push_str("</svg>\n");
    out
}

/// Pixel size of a drawing from its root element's `width` and `height` attributes.
fn drawing_size(svg: &str) -> (f64, f64) {
    let root = svg.split('>').next().unwrap_or_default();
    let attr = |name: &str| {
        root.split(&format!(" {name}=\""))
            .nth(1)
            .and_then(|rest| rest.split('"').next())
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(1000.0)
    };
    (attr("width"), attr("height"))
}

/// Drawings next to each other, each under its caption, in one SVG.
pub fn side_by_side(panels: &[(&str, &str)], title: &str) -> String {
    let (gap, head) = (20.0, 40.0);
    let sizes: Vec<(f64, f64)> = panels.iter().map(|(_, s)| drawing_size(s)).collect();
    let width: f64 =
        sizes.iter().map(|s| s.0).sum::<f64>() + gap * (panels.len().max(1) - 1) as f64;
    let height = sizes.iter().map(|s| s.1).fold(0.0, f64::max) + head;
    let mut out = String::new();
    let _ = writeln!(
        out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width:.0} {height:.0}" width="{width:.0}" height="{height:.0}" font-family="sans-serif">"#
    );
    let _ = writeln!(out, "<title>{}</title>", escape(title));
    let mut x = 0.0;
    for ((caption, svg), (w, _)) in panels.iter().zip(&sizes) {
        let _ = writeln!(
            out,
            r#"<text x="{:.0}" y="28" font-size="24" text-anchor="middle">{}</text>"#,
            x + w / 2.0,
            escape(caption)
        );
        let _ = writeln!(out, r#"<g transform="translate({x:.0},{head:.0})">"#);
        out.push_str(svg.trim_end());
        out.push_str("\n</g>\n");
        x += w + gap;
    }
    out.push_str("</svg>\n");
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toolpath::{PathRole, ToolPath};

    /// A road whose width steps at every vertex is drawn as pieces inside one translucent
    /// group, with no opacity of their own (their round caps would darken each join).
    #[test]
    fn a_road_of_varying_width_is_one_translucent_group() {
        let points: Vec<DVec2> = (0..6).map(|k| DVec2::new(k as f64, 0.0)).collect();
        let road = |y: f64| ToolPath {
            role: PathRole::Offset {
                island: 0,
                n: 0,
                i: 1,
            },
            points: points.iter().map(|p| *p + DVec2::new(0.0, y)).collect(),
            closed: false,
            width_factors: vec![1.0, 1.1, 1.2, 1.3, 1.4, 1.5],
            composition: vec![0.5, 0.5],
            seam_at_corner: false,
        };
        let islands = [Region::new(
            vec![
                DVec2::new(-1.0, -1.0),
                DVec2::new(6.0, -1.0),
                DVec2::new(6.0, 2.0),
                DVec2::new(-1.0, 2.0),
            ],
            vec![],
        )];
        let svg = roads_svg(
            &[road(0.0), road(0.4)],
            &RoadsInput {
                title: "widths",
                islands: &islands,
                road_width_mm: 0.4,
                voids: &[],
                void_cell_mm: 0.05,
                mixer_limited: &[],
            },
        );
        assert_eq!(svg.matches(r#"<g opacity="0.85">"#).count(), 2, "{svg}");
        assert_eq!(svg.matches("</g>").count(), 2, "{svg}");
        assert!(!svg.contains("stroke-opacity"), "{svg}");
        // Five pieces a road (the width steps by 0.1 at every vertex), inside its group.
        let first = svg
            .split(r#"<g opacity="0.85">"#)
            .nth(1)
            .unwrap_or_default();
        let group = first.split("</g>").next().unwrap_or_default();
        assert_eq!(group.matches("<polyline").count(), 5, "{group}");
    }
}
