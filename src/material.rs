//! Material compositions and gradient functions: the paper's equations (2), (3), (4),
//! (6) and (7).
//!
//! A [`Composition`] is the material array M of §3.2: one volume fraction per primary
//! material (one per syringe), each finite and non-negative, summing to 1 within
//! [`Tolerances::composition_sum`](crate::geom::Tolerances). A [`GradientFunction`] is
//! f(d) of eq (3); [`contour_composition`] is eq (4), [`offset_composition`] eq (6) and
//! [`step_width`] eq (7). The formulas are written exactly as in the paper so the worked
//! example of §3.2 reproduces to the last bit that f64 allows.

use serde::{Deserialize, Serialize};

/// Why a composition or gradient function was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MaterialError {
    #[error("composition is empty; give one fraction per material")]
    Empty,
    #[error("composition has {got} fractions but there are {expected} materials")]
    WrongLength { expected: usize, got: usize },
    #[error("fraction {index} is {value}, not a finite number")]
    NotFinite { index: usize, value: f64 },
    #[error("fraction {index} is {value}, below 0")]
    Negative { index: usize, value: f64 },
    #[error("fractions sum to {sum}, not 1 (tolerance {tolerance:e})")]
    BadSum { sum: f64, tolerance: f64 },
    #[error("linear f(d) = A d + B must satisfy eq (3): f(0) = 0 and f(1) = 1, but A = {a}, B = {b} gives f(0) = {f0}, f(1) = {f1}")]
    LinearEndpoints { a: f64, b: f64, f0: f64, f1: f64 },
    #[error("power exponent must be finite and above 0, got {0}")]
    BadExponent(f64),
    #[error("table needs at least 2 points, got {0}")]
    TableTooShort(usize),
    #[error("table point {index} ({d}, {f}) is not finite")]
    TableNotFinite { index: usize, d: f64, f: f64 },
    #[error("table must start at (0, 0) and end at (1, 1) (eq (3)); it runs from ({d0}, {f0}) to ({d1}, {f1})")]
    TableEndpoints { d0: f64, f0: f64, d1: f64, f1: f64 },
    #[error("table d values must strictly increase; point {index} has d = {d} after {prev}")]
    TableNotIncreasing { index: usize, d: f64, prev: f64 },
    #[error("table f values must not decrease (a monotone gradient); point {index} has f = {f} after {prev}")]
    TableNotMonotone { index: usize, f: f64, prev: f64 },
}

/// A material array M: volume fractions of the n primary materials, in syringe order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Composition(Vec<f64>);

impl Composition {
    /// A validated composition: finite, non-negative, summing to 1 within `sum_tolerance`.
    pub fn new(fractions: Vec<f64>, sum_tolerance: f64) -> Result<Self, MaterialError> {
        Self::check(&fractions, sum_tolerance)?;
        Ok(Composition(fractions))
    }

    /// A validated composition of exactly `materials` fractions.
    pub fn with_len(
        fractions: Vec<f64>,
        materials: usize,
        sum_tolerance: f64,
    ) -> Result<Self, MaterialError> {
        if fractions.len() != materials {
            return Err(MaterialError::WrongLength {
                expected: materials,
                got: fractions.len(),
            });
        }
        Self::new(fractions, sum_tolerance)
    }

    fn check(f: &[f64], sum_tolerance: f64) -> Result<(), MaterialError> {
        if f.is_empty() {
            return Err(MaterialError::Empty);
        }
        for (index, &value) in f.iter().enumerate() {
            if !value.is_finite() {
                return Err(MaterialError::NotFinite { index, value });
            }
            if value < -sum_tolerance {
                return Err(MaterialError::Negative { index, value });
            }
        }
        let sum: f64 = f.iter().sum();
        if (sum - 1.0).abs() > sum_tolerance {
            return Err(MaterialError::BadSum {
                sum,
                tolerance: sum_tolerance,
            });
        }
        Ok(())
    }

    /// A pure material `index` of `n` (1 in one syringe, 0 elsewhere).
    pub fn pure(index: usize, n: usize) -> Self {
        let mut v = vec![0.0; n];
        if index < n {
            v[index] = 1.0;
        }
        Composition(v)
    }

    /// Wrap fractions computed by this module's equations from valid compositions
    /// (convex combinations), which are valid up to rounding.
    fn derived(fractions: Vec<f64>) -> Self {
        Composition(fractions)
    }

    pub fn fractions(&self) -> &[f64] {
        &self.0
    }

    pub fn len(&self) -> usize {
        self.0.len()
    }

    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Largest absolute difference between two compositions' fractions.
    pub fn max_abs_diff(&self, other: &Composition) -> f64 {
        max_fraction_difference(&self.0, &other.0)
    }
}

/// Largest absolute difference between two fraction arrays (compositions as plain
/// slices: a designed one against what left the nozzle).
pub fn max_fraction_difference(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max)
}

/// The step width array W of eq (7): the per-material change of composition from one
/// equal distance offset to the next within a sub-region. Sums to 0.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct StepWidth(Vec<f64>);

impl StepWidth {
    pub fn components(&self) -> &[f64] {
        &self.0
    }
}

/// f(d) of eq (3): maps the normalised distance d ∈ [0, 1] from Ci to the fraction of the
/// way from M(Ci) to M(Ce). Every variant satisfies f(0) = 0 and f(1) = 1 once validated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GradientFunction {
    /// f = A d + B (the paper's linear case); eq (3) forces A = 1, B = 0.
    Linear { a: f64, b: f64 },
    /// f = d^p, p > 0 (p > 1 keeps the inner material longer).
    Power(f64),
    /// f = 3d² − 2d³: flat at both boundaries.
    Smoothstep,
    /// Piecewise linear through user (d, f) points from (0, 0) to (1, 1).
    Table(Vec<[f64; 2]>),
}

impl GradientFunction {
    pub const LINEAR: GradientFunction = GradientFunction::Linear { a: 1.0, b: 0.0 };

    /// Check the eq (3) endpoint conditions and the function's own parameters.
    pub fn validate(&self, tolerance: f64) -> Result<(), MaterialError> {
        match self {
            GradientFunction::Linear { a, b } => {
                let (f0, f1) = (*b, a + b);
                if !a.is_finite()
                    || !b.is_finite()
                    || f0.abs() > tolerance
                    || (f1 - 1.0).abs() > tolerance
                {
                    return Err(MaterialError::LinearEndpoints {
                        a: *a,
                        b: *b,
                        f0,
                        f1,
                    });
                }
            }
            GradientFunction::Power(p) => {
                if !p.is_finite() || *p <= 0.0 {
                    return Err(MaterialError::BadExponent(*p));
                }
            }
            GradientFunction::Smoothstep => {}
            GradientFunction::Table(pts) => {
                if pts.len() < 2 {
                    return Err(MaterialError::TableTooShort(pts.len()));
                }
                for (index, &[d, f]) in pts.iter().enumerate() {
                    if !d.is_finite() || !f.is_finite() {
                        return Err(MaterialError::TableNotFinite { index, d, f });
                    }
                }
                let [d0, f0] = pts[0];
                let [d1, f1] = pts[pts.len() - 1];
                if d0.abs() > tolerance
                    || f0.abs() > tolerance
                    || (d1 - 1.0).abs() > tolerance
                    || (f1 - 1.0).abs() > tolerance
                {
                    return Err(MaterialError::TableEndpoints { d0, f0, d1, f1 });
                }
                for index in 1..pts.len() {
                    let [d, f] = pts[index];
                    let [pd, pf] = pts[index - 1];
                    if d <= pd {
                        return Err(MaterialError::TableNotIncreasing { index, d, prev: pd });
                    }
                    if f < pf {
                        return Err(MaterialError::TableNotMonotone { index, f, prev: pf });
                    }
                }
            }
        }
        Ok(())
    }

    /// f(d) for d ∈ [0, 1] (clamped).
    pub fn eval(&self, d: f64) -> f64 {
        let d = d.clamp(0.0, 1.0);
        match self {
            GradientFunction::Linear { a, b } => a * d + b,
            GradientFunction::Power(p) => d.powf(*p),
            GradientFunction::Smoothstep => d * d * (3.0 - 2.0 * d),
            GradientFunction::Table(pts) => {
                let k = pts.partition_point(|p| p[0] < d);
                if k == 0 {
                    return pts[0][1];
                }
                if k >= pts.len() {
                    return pts[pts.len() - 1][1];
                }
                let [d0, f0] = pts[k - 1];
                let [d1, f1] = pts[k];
                f0 + (f1 - f0) * (d - d0) / (d1 - d0)
            }
        }
    }

    /// Is f non-decreasing (so compositions change monotonically from Ci to Ce)?
    pub fn is_monotone(&self) -> bool {
        match self {
            GradientFunction::Linear { a, .. } => *a >= 0.0,
            _ => true,
        }
    }
}

/// Eq (1): the number of segments m on each radial line, `int(L_short / R_mach + 0.5)`.
pub fn segment_count(l_short_mm: f64, r_mach_mm: f64) -> u32 {
    round_half_up(l_short_mm / r_mach_mm)
}

/// Eq (5): the number of equal distance offsets `N_max = int(D_max / D_noz + 0.5)`.
pub fn offset_count(d_max_mm: f64, nozzle_mm: f64) -> u32 {
    round_half_up(d_max_mm / nozzle_mm)
}

fn round_half_up(x: f64) -> u32 {
    let v = (x + 0.5).floor();
    if v.is_finite() && v > 0.0 {
        v.min(u32::MAX as f64) as u32
    } else {
        0
    }
}

/// Eq (2): the normalised distance of contour j (1-based) from Ci, `d_j = (j − 1) / m`.
pub fn contour_distance(j: u32, m: u32) -> f64 {
    (j as f64 - 1.0) / m as f64
}

/// Eq (4): the composition of a contour at normalised distance `d` from Ci,
/// `M = f(d) · (M(Ce) − M(Ci)) + M(Ci)`.
pub fn contour_composition(
    f: &GradientFunction,
    d: f64,
    inner: &Composition,
    outer: &Composition,
) -> Composition {
    let fd = f.eval(d);
    Composition::derived(
        inner
            .0
            .iter()
            .zip(&outer.0)
            .map(|(mi, me)| fd * (me - mi) + mi)
            .collect(),
    )
}

/// Which bounding contour the equal distance offsets of a sub-region start from (eq (6)).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum OffsetDirection {
    /// Offsets of C(n+1) towards C(n); i counts from C(n+1) (the paper's worked example).
    #[default]
    Inward,
    /// Offsets of C(n) towards C(n+1); i counts from C(n).
    Outward,
}

/// Eq (6): the composition of the i-th equal distance offset (1 ≤ i ≤ N_max − 1) in
/// sub-region S(n,n+1) bounded by contours with compositions `m_n` and `m_n1`.
pub fn offset_composition(
    direction: OffsetDirection,
    i: u32,
    n_max: u32,
    m_n: &Composition,
    m_n1: &Composition,
) -> Composition {
    let t = match direction {
        OffsetDirection::Inward => i as f64 / n_max as f64,
        OffsetDirection::Outward => (n_max as f64 - i as f64) / n_max as f64,
    };
    Composition::derived(
        m_n.0
            .iter()
            .zip(&m_n1.0)
            .map(|(a, b)| t * (a - b) + b)
            .collect(),
    )
}

/// Eq (7): `W(S(n,n+1)) = M(S(n,n+1), i+1) − M(S(n,n+1), i)`; constant within a sub-region
/// because eq (6) is linear in i, so it is evaluated at i = 1.
pub fn step_width(
    direction: OffsetDirection,
    n_max: u32,
    m_n: &Composition,
    m_n1: &Composition,
) -> StepWidth {
    let a = offset_composition(direction, 1, n_max, m_n, m_n1);
    let b = offset_composition(direction, 2, n_max, m_n, m_n1);
    StepWidth(b.0.iter().zip(&a.0).map(|(y, x)| y - x).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn c(v: &[f64]) -> Composition {
        Composition::new(v.to_vec(), 1e-12).unwrap()
    }

    fn close(a: &Composition, b: &[f64]) {
        for (x, y) in a.fractions().iter().zip(b) {
            assert!((x - y).abs() <= 1e-12, "{a:?} != {b:?}");
        }
    }

    #[test]
    fn paper_worked_example_eq4() {
        // §3.2: m = 10, M(Ci) = [1, 0], M(Ce) = [0, 1], linear f.
        let (mi, me) = (c(&[1.0, 0.0]), c(&[0.0, 1.0]));
        let f = GradientFunction::LINEAR;
        let c4 = contour_composition(&f, contour_distance(4, 10), &mi, &me);
        let c5 = contour_composition(&f, contour_distance(5, 10), &mi, &me);
        close(&c4, &[0.7, 0.3]);
        close(&c5, &[0.6, 0.4]);
    }

    #[test]
    fn paper_worked_example_eq6_eq7() {
        let (c4, c5) = (c(&[0.7, 0.3]), c(&[0.6, 0.4]));
        let want = [[0.625, 0.375], [0.65, 0.35], [0.675, 0.325]];
        for (i, w) in (1..=3).zip(want) {
            close(
                &offset_composition(OffsetDirection::Inward, i, 4, &c4, &c5),
                &w,
            );
            // Outward counting from C4 reaches the same offsets in the other order.
            close(
                &offset_composition(OffsetDirection::Outward, 4 - i, 4, &c4, &c5),
                &w,
            );
        }
        let w = step_width(OffsetDirection::Inward, 4, &c4, &c5);
        assert!((w.components()[0] - 0.025).abs() <= 1e-12);
        assert!((w.components()[1] + 0.025).abs() <= 1e-12);
    }

    #[test]
    fn eq1_and_eq5_round_half_up() {
        assert_eq!(segment_count(20.0, 2.0), 10); // the paper's annulus: m = 10
        assert_eq!(segment_count(2.9, 2.0), 1);
        assert_eq!(segment_count(3.0, 2.0), 2); // 1.5 rounds up
        assert_eq!(segment_count(0.9, 2.0), 0);
        assert_eq!(offset_count(2.0, 0.5), 4); // N_max = 4 in S4,5
        assert_eq!(offset_count(1.2, 0.5), 2); // 2.4 -> 2
        assert_eq!(offset_count(1.25, 0.5), 3); // 2.5 -> 3
        assert_eq!(segment_count(f64::NAN, 1.0), 0);
    }

    #[test]
    fn eq2_distances() {
        assert_eq!(contour_distance(1, 10), 0.0);
        assert_eq!(contour_distance(11, 10), 1.0);
        assert_eq!(contour_distance(4, 10), 0.3);
    }

    #[test]
    fn composition_validation_names_the_problem() {
        assert_eq!(
            Composition::with_len(vec![1.0], 2, 1e-9),
            Err(MaterialError::WrongLength {
                expected: 2,
                got: 1
            })
        );
        assert!(matches!(
            Composition::new(vec![0.5, 0.6], 1e-9),
            Err(MaterialError::BadSum { .. })
        ));
        assert!(matches!(
            Composition::new(vec![f64::NAN, 1.0], 1e-9),
            Err(MaterialError::NotFinite { index: 0, .. })
        ));
        assert!(matches!(
            Composition::new(vec![-0.5, 1.5], 1e-9),
            Err(MaterialError::Negative { index: 0, .. })
        ));
        assert_eq!(Composition::new(vec![], 1e-9), Err(MaterialError::Empty));
    }

    #[test]
    fn gradient_functions_meet_eq3() {
        let tol = 1e-12;
        let fs = [
            GradientFunction::LINEAR,
            GradientFunction::Power(2.0),
            GradientFunction::Smoothstep,
            GradientFunction::Table(vec![[0.0, 0.0], [0.5, 0.8], [1.0, 1.0]]),
        ];
        for f in &fs {
            f.validate(tol).unwrap();
            assert_eq!(f.eval(0.0), 0.0, "{f:?}");
            assert_eq!(f.eval(1.0), 1.0, "{f:?}");
            let mut prev = 0.0;
            for k in 0..=100 {
                let v = f.eval(k as f64 / 100.0);
                assert!(v >= prev && (0.0..=1.0).contains(&v), "{f:?} at {k}");
                prev = v;
            }
        }
        assert_eq!(
            GradientFunction::Table(vec![[0.0, 0.0], [0.5, 0.8], [1.0, 1.0]]).eval(0.25),
            0.4
        );
        assert!(GradientFunction::Linear { a: 2.0, b: 0.0 }
            .validate(tol)
            .is_err());
        assert!(GradientFunction::Power(0.0).validate(tol).is_err());
        assert!(
            GradientFunction::Table(vec![[0.0, 0.0], [0.6, 0.5], [0.5, 0.6], [1.0, 1.0]])
                .validate(tol)
                .is_err()
        );
        assert!(
            GradientFunction::Table(vec![[0.0, 0.0], [0.5, 0.8], [0.7, 0.6], [1.0, 1.0]])
                .validate(tol)
                .is_err()
        );
        assert!(GradientFunction::Table(vec![[0.0, 0.1], [1.0, 1.0]])
            .validate(tol)
            .is_err());
    }
}
