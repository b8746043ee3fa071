//! The job file (`docs/job-format.md`): what to build, from which materials, with which
//! gradient, on which process settings. TOML, parsed with serde, every unknown key
//! refused, every value validated with an error that names the key.
//!
//! Pure: [`Job::from_toml`] takes the text (and a name for messages); reading the file
//! is the caller's business.

use crate::edo::{shapes, GradientDesign, Pattern, PlanOptions, Subdivision};
use crate::geom::{Region, Tolerances};
use crate::material::{Composition, GradientFunction, OffsetDirection};
use glam::DVec2;
use serde::Deserialize;

/// A job file that cannot be used, with where and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum JobError {
    /// The TOML itself is malformed or has unknown/missing keys (message has line and column).
    #[error("{source_name}: {message}")]
    Syntax {
        source_name: String,
        message: String,
    },
    /// A value is out of range or inconsistent; `key` is its dotted path.
    #[error("{source_name}: {key}: {message}")]
    Invalid {
        source_name: String,
        key: String,
        message: String,
    },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawJob {
    name: String,
    geometry: RawGeometry,
    materials: RawMaterials,
    gradient: RawGradient,
    process: RawProcess,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGeometry {
    polygon: Option<RawRegion>,
    regions: Option<Vec<RawRegion>>,
    height: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRegion {
    outer: LoopSpec,
    #[serde(default)]
    holes: Vec<LoopSpec>,
}

/// A closed loop: explicit points, or a primitive.
#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum LoopSpec {
    Points(Vec<[f64; 2]>),
    Circle { circle: CircleSpec },
    Ellipse { ellipse: EllipseSpec },
    Rect { rect: RectSpec },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CircleSpec {
    center: [f64; 2],
    radius: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct EllipseSpec {
    center: [f64; 2],
    radii: [f64; 2],
    #[serde(default)]
    rotation: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RectSpec {
    min: [f64; 2],
    max: [f64; 2],
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMaterials {
    names: Vec<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGradient {
    #[serde(default = "default_pattern")]
    pattern: String,
    inner: Vec<f64>,
    outer: Vec<f64>,
    #[serde(default)]
    function: Option<FunctionSpec>,
    #[serde(default)]
    subdivision: Option<Subdivision>,
    #[serde(default)]
    direction: Option<OffsetDirection>,
    depth: Option<f64>,
    angle: Option<f64>,
}

fn default_pattern() -> String {
    "growth-rings".to_string()
}

#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum FunctionSpec {
    Named(String),
    Power { power: f64 },
    Table { table: Vec<[f64; 2]> },
    Linear { linear: LinearSpec },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct LinearSpec {
    a: f64,
    b: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawProcess {
    r_mach: f64,
    nozzle: f64,
    layer: Option<LayerSpec>,
    boundary_offset: Option<f64>,
    radial_lines: Option<usize>,
    field_cell: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum LayerSpec {
    Uniform(f64),
    Range { min: f64, max: f64 },
}

/// Layer heights: uniform when `min_mm == max_mm`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct LayerHeights {
    pub min_mm: f64,
    pub max_mm: f64,
}

/// What the job builds.
#[derive(Clone, Debug, PartialEq)]
pub enum Geometry {
    /// Islands (outer loop + holes) extruded from z = 0 to `height_mm`.
    Extruded {
        islands: Vec<Region>,
        height_mm: f64,
    },
}

/// A validated job.
#[derive(Clone, Debug, PartialEq)]
pub struct Job {
    pub name: String,
    pub geometry: Geometry,
    /// One material per syringe, in syringe order.
    pub materials: Vec<String>,
    pub design: GradientDesign,
    pub plan: PlanOptions,
    pub layers: LayerHeights,
}

/// One layer to plan: its index, top z, thickness and islands.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerSlice {
    pub index: usize,
    pub z_mm: f64,
    pub thickness_mm: f64,
    pub islands: Vec<Region>,
}

impl Job {
    /// Parse and validate a job from TOML text. `source_name` (usually the file path)
    /// prefixes every message.
    pub fn from_toml(text: &str, source_name: &str) -> Result<Job, JobError> {
        let raw: RawJob = toml::from_str(text).map_err(|e| JobError::Syntax {
            source_name: source_name.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let bad = |key: &str, message: String| JobError::Invalid {
            source_name: source_name.to_string(),
            key: key.to_string(),
            message,
        };
        let tolerances = Tolerances::default();

        if raw.name.trim().is_empty() {
            return Err(bad("name", "must not be empty".into()));
        }
        // Materials.
        let materials = raw.materials.names;
        if materials.is_empty() {
            return Err(bad(
                "materials.names",
                "list at least one material (one per syringe)".into(),
            ));
        }
        if materials.len() > 8 {
            return Err(bad(
                "materials.names",
                format!(
                    "{} materials listed; the machine has at most 8 syringes",
                    materials.len()
                ),
            ));
        }
        for (i, n) in materials.iter().enumerate() {
            if n.trim().is_empty() {
                return Err(bad("materials.names", format!("name {i} is empty")));
            }
            if materials[..i].contains(n) {
                return Err(bad("materials.names", format!("\"{n}\" is listed twice")));
            }
        }
        // Process.
        let p = raw.process;
        positive(p.r_mach, "process.r_mach", &bad)?;
        positive(p.nozzle, "process.nozzle", &bad)?;
        let mut plan = PlanOptions::new(p.r_mach, p.nozzle);
        plan.tolerances = tolerances;
        if let Some(b) = p.boundary_offset {
            if !b.is_finite() || b < 0.0 {
                return Err(bad(
                    "process.boundary_offset",
                    format!("must be a distance of 0 or more in mm, got {b}"),
                ));
            }
            plan.boundary_offset_mm = b;
        }
        if let Some(n) = p.radial_lines {
            if !(8..=100_000).contains(&n) {
                return Err(bad(
                    "process.radial_lines",
                    format!("must be between 8 and 100000, got {n}"),
                ));
            }
            plan.radial_lines = n;
        }
        if let Some(c) = p.field_cell {
            positive(c, "process.field_cell", &bad)?;
            plan.field_cell_mm = Some(c);
        }
        let layers = match p.layer {
            None => LayerHeights {
                min_mm: p.nozzle / 2.0,
                max_mm: p.nozzle / 2.0,
            },
            Some(LayerSpec::Uniform(h)) => {
                positive(h, "process.layer", &bad)?;
                LayerHeights {
                    min_mm: h,
                    max_mm: h,
                }
            }
            Some(LayerSpec::Range { min, max }) => {
                positive(min, "process.layer.min", &bad)?;
                positive(max, "process.layer.max", &bad)?;
                if min > max {
                    return Err(bad(
                        "process.layer",
                        format!("min ({min}) is above max ({max})"),
                    ));
                }
                LayerHeights {
                    min_mm: min,
                    max_mm: max,
                }
            }
        };
        // Gradient.
        let g = raw.gradient;
        let n = materials.len();
        let inner = Composition::with_len(g.inner, n, tolerances.composition_sum)
            .map_err(|e| bad("gradient.inner", format!("M(Ci): {e}")))?;
        let outer = Composition::with_len(g.outer, n, tolerances.composition_sum)
            .map_err(|e| bad("gradient.outer", format!("M(Ce): {e}")))?;
        let function = match g.function {
            None => GradientFunction::LINEAR,
            Some(FunctionSpec::Named(s)) => match s.as_str() {
                "linear" => GradientFunction::LINEAR,
                "smoothstep" => GradientFunction::Smoothstep,
                other => {
                    return Err(bad(
                        "gradient.function",
                        format!("unknown function \"{other}\"; use \"linear\", \"smoothstep\", {{ power = P }}, {{ table = [[d, f], ...] }} or {{ linear = {{ a = A, b = B }} }}"),
                    ))
                }
            },
            Some(FunctionSpec::Power { power }) => GradientFunction::Power(power),
            Some(FunctionSpec::Table { table }) => GradientFunction::Table(table),
            Some(FunctionSpec::Linear { linear }) => GradientFunction::Linear {
                a: linear.a,
                b: linear.b,
            },
        };
        function
            .validate(1e-9)
            .map_err(|e| bad("gradient.function", e.to_string()))?;
        let only_for = |key: &str, value: &Option<f64>, pattern: &str| -> Result<(), JobError> {
            if value.is_some() && g.pattern != pattern {
                return Err(bad(
                    &format!("gradient.{key}"),
                    format!(
                        "applies to pattern = \"{pattern}\" only, this job's pattern is \"{}\"",
                        g.pattern
                    ),
                ));
            }
            Ok(())
        };
        only_for("depth", &g.depth, "crown")?;
        only_for("angle", &g.angle, "fibers")?;
        let pattern = match g.pattern.as_str() {
            "growth-rings" => Pattern::GrowthRings,
            "crown" => {
                let depth = g.depth.ok_or_else(|| {
                    bad(
                        "gradient.depth",
                        "pattern = \"crown\" needs depth, the graded shell thickness under the outer surface in mm".into(),
                    )
                })?;
                positive(depth, "gradient.depth", &bad)?;
                Pattern::Crown { depth_mm: depth }
            }
            "fibers" => {
                let angle = g.angle.unwrap_or(0.0);
                if !angle.is_finite() {
                    return Err(bad(
                        "gradient.angle",
                        format!("must be a finite angle in degrees, got {angle}"),
                    ));
                }
                Pattern::Fibers { angle_deg: angle }
            }
            other => {
                return Err(bad(
                    "gradient.pattern",
                    format!(
                    "unknown pattern \"{other}\"; use \"growth-rings\", \"crown\" or \"fibers\""
                ),
                ))
            }
        };
        if let Some(s) = g.subdivision {
            if !matches!(pattern, Pattern::GrowthRings) && s != Subdivision::Auto {
                return Err(bad(
                    "gradient.subdivision",
                    "applies to pattern = \"growth-rings\" only (crown contours are offsets, fiber contours lines)".into(),
                ));
            }
            plan.subdivision = s;
        }
        if let Some(d) = g.direction {
            plan.direction = d;
        }
        // Geometry.
        let geo = raw.geometry;
        positive(geo.height, "geometry.height", &bad)?;
        let specs: Vec<(String, RawRegion)> = match (geo.polygon, geo.regions) {
            (Some(_), Some(_)) => {
                return Err(bad(
                    "geometry",
                    "give either polygon (one island) or regions (several), not both".into(),
                ))
            }
            (None, None) => {
                return Err(bad(
                    "geometry",
                    "missing polygon = { outer = [...], holes = [...] } or regions = [...]".into(),
                ))
            }
            (Some(r), None) => vec![("geometry.polygon".to_string(), r)],
            (None, Some(rs)) => {
                if rs.is_empty() {
                    return Err(bad("geometry.regions", "is empty".into()));
                }
                rs.into_iter()
                    .enumerate()
                    .map(|(i, r)| (format!("geometry.regions[{i}]"), r))
                    .collect()
            }
        };
        let mut islands = Vec::with_capacity(specs.len());
        for (key, r) in specs {
            let outer = loop_points(&r.outer, &format!("{key}.outer"), tolerances.chord_mm, &bad)?;
            let holes = r
                .holes
                .iter()
                .enumerate()
                .map(|(i, h)| {
                    loop_points(h, &format!("{key}.holes[{i}]"), tolerances.chord_mm, &bad)
                })
                .collect::<Result<Vec<_>, _>>()?;
            let region = Region::new(outer, holes).normalised(&tolerances);
            region
                .validate(&tolerances)
                .map_err(|e| bad(&key, e.to_string()))?;
            islands.push(region);
        }
        for i in 0..islands.len() {
            for j in 0..i {
                if islands_overlap(&islands[i], &islands[j]) {
                    return Err(bad(
                        "geometry.regions",
                        format!("regions {j} and {i} overlap; islands must be disjoint (put a region inside another's hole, not over it)"),
                    ));
                }
            }
        }
        Ok(Job {
            name: raw.name,
            geometry: Geometry::Extruded {
                islands,
                height_mm: geo.height,
            },
            materials,
            design: GradientDesign {
                pattern,
                inner,
                outer,
                function,
            },
            plan,
            layers,
        })
    }

    /// The layers to plan: an extruded polygon is cut into equal layers no thicker than
    /// the maximum layer height; `z_mm` is each layer's top.
    pub fn layer_slices(&self) -> Vec<LayerSlice> {
        match &self.geometry {
            Geometry::Extruded { islands, height_mm } => {
                let count = ((height_mm / self.layers.max_mm) - 1e-9).ceil().max(1.0) as usize;
                let t = height_mm / count as f64;
                (0..count)
                    .map(|index| LayerSlice {
                        index,
                        z_mm: t * (index + 1) as f64,
                        thickness_mm: t,
                        islands: islands.clone(),
                    })
                    .collect()
            }
        }
    }
}

fn positive<E>(v: f64, key: &str, bad: &impl Fn(&str, String) -> E) -> Result<(), E> {
    if !v.is_finite() || v <= 0.0 {
        return Err(bad(
            key,
            format!("must be a positive number of mm, got {v}"),
        ));
    }
    Ok(())
}

fn loop_points<E>(
    spec: &LoopSpec,
    key: &str,
    chord_mm: f64,
    bad: &impl Fn(&str, String) -> E,
) -> Result<Vec<DVec2>, E> {
    let finite = |v: &[f64], what: &str| -> Result<(), E> {
        if v.iter().all(|x| x.is_finite()) {
            Ok(())
        } else {
            Err(bad(key, format!("{what} is not finite")))
        }
    };
    match spec {
        LoopSpec::Points(pts) => {
            if let Some(i) = pts
                .iter()
                .position(|p| !p[0].is_finite() || !p[1].is_finite())
            {
                return Err(bad(key, format!("point {i} is not a finite number")));
            }
            Ok(pts.iter().map(|p| DVec2::new(p[0], p[1])).collect())
        }
        LoopSpec::Circle { circle } => {
            finite(
                &[circle.center[0], circle.center[1], circle.radius],
                "circle",
            )?;
            positive(circle.radius, &format!("{key}.circle.radius"), bad)?;
            Ok(shapes::circle(
                DVec2::from(circle.center),
                circle.radius,
                chord_mm,
            ))
        }
        LoopSpec::Ellipse { ellipse } => {
            finite(
                &[
                    ellipse.center[0],
                    ellipse.center[1],
                    ellipse.radii[0],
                    ellipse.radii[1],
                    ellipse.rotation,
                ],
                "ellipse",
            )?;
            positive(ellipse.radii[0], &format!("{key}.ellipse.radii[0]"), bad)?;
            positive(ellipse.radii[1], &format!("{key}.ellipse.radii[1]"), bad)?;
            let c = DVec2::from(ellipse.center);
            let rot = DVec2::from_angle(ellipse.rotation.to_radians());
            let big = ellipse.radii[0].max(ellipse.radii[1]);
            Ok(shapes::circle(DVec2::ZERO, big, chord_mm)
                .into_iter()
                .map(|p| {
                    c + rot.rotate(DVec2::new(
                        p.x * ellipse.radii[0] / big,
                        p.y * ellipse.radii[1] / big,
                    ))
                })
                .collect())
        }
        LoopSpec::Rect { rect } => {
            finite(
                &[rect.min[0], rect.min[1], rect.max[0], rect.max[1]],
                "rect",
            )?;
            let (lo, hi) = (DVec2::from(rect.min), DVec2::from(rect.max));
            if hi.x <= lo.x || hi.y <= lo.y {
                return Err(bad(
                    key,
                    format!(
                        "rect max {:?} must be above min {:?} in x and y",
                        rect.max, rect.min
                    ),
                ));
            }
            Ok(vec![lo, DVec2::new(hi.x, lo.y), hi, DVec2::new(lo.x, hi.y)])
        }
    }
}

/// Do two islands' materials overlap (an edge crossing, or one inside the other's material)?
fn islands_overlap(a: &Region, b: &Region) -> bool {
    let loops: Vec<&[DVec2]> = a.loops().chain(b.loops()).map(|l| l.as_slice()).collect();
    if crate::geom::first_crossing(&loops).is_some() {
        return true;
    }
    a.contains(b.outer[0]) || b.contains(a.outer[0])
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"
name = "t"
[geometry]
polygon = { outer = { circle = { center = [0.0, 0.0], radius = 30.0 } }, holes = [{ circle = { center = [0.0, 0.0], radius = 10.0 } }] }
height = 0.4
[materials]
names = ["A", "B"]
[gradient]
pattern = "growth-rings"
inner = [1.0, 0.0]
outer = [0.0, 1.0]
function = "linear"
subdivision = "auto"
[process]
r_mach = 2.0
nozzle = 0.5
"#;

    fn err(text: &str) -> String {
        Job::from_toml(text, "job.toml").unwrap_err().to_string()
    }

    #[test]
    fn good_job_parses() {
        let job = Job::from_toml(GOOD, "job.toml").unwrap();
        assert_eq!(job.materials, ["A", "B"]);
        assert_eq!(job.plan.r_mach_mm, 2.0);
        let layers = job.layer_slices();
        assert_eq!(layers.len(), 2);
        assert!((layers[1].z_mm - 0.4).abs() < 1e-12);
    }

    #[test]
    fn errors_name_the_key() {
        let e = err(&GOOD.replace("inner = [1.0, 0.0]", "inner = [0.5, 0.6]"));
        assert!(e.contains("gradient.inner") && e.contains("sum"), "{e}");
        let e = err(&GOOD.replace("inner = [1.0, 0.0]", "inner = [1.0]"));
        assert!(
            e.contains("gradient.inner") && e.contains("2 materials"),
            "{e}"
        );
        let e = err(&GOOD.replace("r_mach = 2.0", "r_mach = -2.0"));
        assert!(e.contains("process.r_mach"), "{e}");
        let e = err(&GOOD.replace("nozzle = 0.5", "nozzle = 0.0"));
        assert!(e.contains("process.nozzle"), "{e}");
        let e = err(&GOOD.replace("r_mach = 2.0", "r_mach = nan"));
        assert!(e.contains("process.r_mach"), "{e}");
        let e = err(&GOOD.replace("pattern = \"growth-rings\"", "pattern = \"zebra\""));
        assert!(e.contains("gradient.pattern"), "{e}");
        let e = err(&GOOD.replace("[process]", "[process]\ncolour = 1"));
        assert!(e.contains("colour"), "{e}");
        let e = err(&GOOD.replace("function = \"linear\"", "function = { power = -1.0 }"));
        assert!(e.contains("gradient.function"), "{e}");
        let e = err(&GOOD.replace("radius = 10.0", "radius = 40.0"));
        assert!(e.contains("geometry.polygon"), "{e}");
        let e = err(&GOOD.replace(
            "function = \"linear\"",
            "function = { linear = { a = 2.0, b = 0.0 } }",
        ));
        assert!(e.contains("eq (3)"), "{e}");
        let e = err("name = ");
        assert!(e.contains("job.toml") && e.contains("line"), "{e}");
    }

    #[test]
    fn bowtie_and_hole_outside_are_refused() {
        let bow = GOOD.replace(
            "outer = { circle = { center = [0.0, 0.0], radius = 30.0 } }, holes = [{ circle = { center = [0.0, 0.0], radius = 10.0 } }]",
            "outer = [[0.0, 0.0], [10.0, 10.0], [10.0, 0.0], [0.0, 10.0]]",
        );
        assert!(err(&bow).contains("crosses"), "{}", err(&bow));
        let outside = GOOD.replace(
            "center = [0.0, 0.0], radius = 10.0",
            "center = [100.0, 0.0], radius = 10.0",
        );
        assert!(err(&outside).contains("not inside"), "{}", err(&outside));
    }
}
