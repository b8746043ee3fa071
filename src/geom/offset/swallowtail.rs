//! Swallowtails of raw offset loops: the little reversed loops where the offset swallows
//! a short edge between two corners it turns into, cut off at their crossing, one
//! crossing at a time in the order the crossing sweep finds them. A crossing that is no
//! swallowtail leaves the offset to the outline.

use super::MAX_SWALLOWTAIL_CUTS;
use crate::geom::{
    crossing_point, crossings, first_crossing, loop_edge, loops, next_in_loop, segments_intersect,
    signed_area2, sweep_rank, Crossing, Shapes,
};
use glam::DVec2;

/// Cut off every swallowtail of `shapes`, one crossing at a time in the order the sweep
/// of [`crate::geom::first_crossing`] would find them; None where a crossing is not a
/// swallowtail or there are more than [`MAX_SWALLOWTAIL_CUTS`].
///
/// One sweep finds every crossing pair. A cut keeps pieces of the two crossing edges
/// and drops the edges between, so the crossings left are pairs of the first sweep
/// whose edges stay whole, and pairs of the two shortened edges (found by testing
/// them against every edge); the other edges keep their order (a cut loop's edges keep
/// theirs round it), so picking the pair the sweep meets first (by [`sweep_rank`]) is
/// the crossing sweeping the cut loops again would find.
pub(super) fn cut_swallowtails(shapes: &mut Shapes, cut_points: &mut Vec<DVec2>) -> Option<()> {
    let raw: Vec<&[DVec2]> = loops(shapes).map(|l| l.as_slice()).collect();
    let Some(mut pending) = crossings(&raw, MAX_PENDING_CROSSINGS) else {
        // Too many to follow.
        return cut_swallowtails_by_sweeping(shapes, cut_points);
    };
    let mut cuts = 0;
    while !pending.is_empty() {
        let all: Vec<&Vec<DVec2>> = loops(shapes).collect();
        let starts = loop_starts(&all);
        let rank = |(l, e): (usize, usize)| {
            let (a, b) = loop_edge(all[l], e);
            sweep_rank(a, b, starts[l] + e)
        };
        let c = *pending
            .iter()
            .min_by_key(|c| (rank(c.second), rank(c.first)))?;
        cuts += 1;
        if cuts > MAX_SWALLOWTAIL_CUTS {
            return None;
        }
        let cut = cut_swallowtail(shapes, &c)?;
        cut_points.push(c.at);
        pending = crossings_after_cut(shapes, &pending, &c, &cut);
    }
    Some(())
}

/// [`cut_swallowtails`] sweeping the loops again after every cut.
fn cut_swallowtails_by_sweeping(shapes: &mut Shapes, cut_points: &mut Vec<DVec2>) -> Option<()> {
    for _ in 0..MAX_SWALLOWTAIL_CUTS {
        let raw: Vec<&[DVec2]> = loops(shapes).map(|l| l.as_slice()).collect();
        let Some(c) = first_crossing(&raw) else {
            return Some(());
        };
        cut_swallowtail(shapes, &c)?;
        cut_points.push(c.at);
    }
    let raw: Vec<&[DVec2]> = loops(shapes).map(|l| l.as_slice()).collect();
    first_crossing(&raw).is_none().then_some(())
}

/// The first edge number of each loop in the order of all loops' edges.
fn loop_starts(all: &[&Vec<DVec2>]) -> Vec<usize> {
    all.iter()
        .scan(0, |n, l| {
            let start = *n;
            *n += l.len();
            Some(start)
        })
        .collect()
}

/// The crossings of `shapes` after [`cut_swallowtail`] cut crossing `c` (`cut`), given
/// every crossing before (`pending`): see [`cut_swallowtails`].
fn crossings_after_cut(
    shapes: &Shapes,
    pending: &[Crossing],
    c: &Crossing,
    cut: &Cut,
) -> Vec<Crossing> {
    let shortened = cut.shortened();
    let edge = |(l, e): (usize, usize)| {
        if l != cut.loop_index {
            return Some((l, e));
        }
        cut.edge(e)
            .filter(|e| !shortened.contains(e))
            .map(|e| (l, e))
    };
    let mut out: Vec<Crossing> = pending
        .iter()
        .filter(|p| (p.first, p.second) != (c.first, c.second))
        .filter_map(|p| {
            Some(Crossing {
                first: edge(p.first)?,
                second: edge(p.second)?,
                at: p.at,
            })
        })
        .collect();
    let all: Vec<&Vec<DVec2>> = loops(shapes).collect();
    let starts = loop_starts(&all);
    let seg = |(l, e): (usize, usize)| loop_edge(all[l], e);
    for s in shortened {
        let me = (cut.loop_index, s);
        let (a, b) = seg(me);
        let (lo, hi) = (a.min(b), a.max(b));
        let n = all[cut.loop_index].len();
        for (l, pts) in all.iter().enumerate() {
            for e in 0..pts.len() {
                // Itself and its neighbours round the loop (the other shortened edge
                // is one) cannot count.
                if l == cut.loop_index
                    && (e == s || e == next_in_loop(s, n) || next_in_loop(e, n) == s)
                {
                    continue;
                }
                let (p, q) = seg((l, e));
                if p.max(q).cmplt(lo).any() || hi.cmplt(p.min(q)).any() {
                    continue;
                }
                if segments_intersect(a, b, p, q) {
                    let (rs, re) = (
                        sweep_rank(a, b, starts[cut.loop_index] + s),
                        sweep_rank(p, q, starts[l] + e),
                    );
                    let (earlier, later) = if rs < re {
                        ((me, (a, b)), ((l, e), (p, q)))
                    } else {
                        (((l, e), (p, q)), (me, (a, b)))
                    };
                    out.push(Crossing {
                        first: earlier.0,
                        second: later.0,
                        at: crossing_point(later.1 .0, later.1 .1, earlier.1 .0, earlier.1 .1),
                    });
                }
            }
        }
    }
    out
}

/// How many crossings [`cut_swallowtails`] follows from one sweep.
const MAX_PENDING_CROSSINGS: usize = 4 * MAX_SWALLOWTAIL_CUTS;

/// What [`cut_swallowtail`] did to its loop: crossing edges `i < j` of a loop of `n`
/// edges, keeping the piece outside them (`outside`: `..=i`, the crossing, `j + 1..`)
/// or between them (the crossing, `i + 1..=j`).
struct Cut {
    loop_index: usize,
    i: usize,
    j: usize,
    outside: bool,
}

impl Cut {
    /// The new number of edge `k` of the cut loop, None where the cut dropped it.
    fn edge(&self, k: usize) -> Option<usize> {
        let (i, j) = (self.i, self.j);
        if self.outside {
            if k <= i {
                Some(k)
            } else if k < j {
                None
            } else {
                Some(k + 1 + i - j)
            }
        } else {
            (i..=j).contains(&k).then(|| k - i)
        }
    }

    /// The new numbers of the two crossing edges, which the cut shortened to the crossing.
    fn shortened(&self) -> [usize; 2] {
        if self.outside {
            [self.i, self.i + 1]
        } else {
            [0, self.j - self.i]
        }
    }
}

/// Cut the loop crossing `c` closes off, if it is a swallowtail: both edges of one loop,
/// at most [`SWALLOWTAIL_EDGES`] apart along it, and the piece between them turning
/// the other way round from the loop. Returns what it cut, None where it did not.
fn cut_swallowtail(shapes: &mut Shapes, c: &Crossing) -> Option<Cut> {
    let ((la, i), (lb, j)) = (c.first, c.second);
    if la != lb {
        return None;
    }
    let (i, j) = (i.min(j), i.max(j));
    let l = shapes.iter_mut().flat_map(|s| s.iter_mut()).nth(la)?;
    let n = l.len();
    let inner = j - i;
    let outer = n - inner;
    let piece: Vec<DVec2> = if inner <= outer {
        std::iter::once(c.at)
            .chain(l[i + 1..=j].iter().copied())
            .collect()
    } else {
        std::iter::once(c.at)
            .chain(l[j + 1..].iter().copied())
            .chain(l[..=i].iter().copied())
            .collect()
    };
    if piece.len() > SWALLOWTAIL_EDGES + 1
        || (signed_area2(&piece) > 0.0) == (signed_area2(l) > 0.0)
    {
        return None;
    }
    let kept: Vec<DVec2> = if inner <= outer {
        l[..=i]
            .iter()
            .copied()
            .chain(std::iter::once(c.at))
            .chain(l[j + 1..].iter().copied())
            .collect()
    } else {
        std::iter::once(c.at)
            .chain(l[i + 1..=j].iter().copied())
            .collect()
    };
    if kept.len() < 3 {
        return None;
    }
    *l = kept;
    Some(Cut {
        loop_index: la,
        i,
        j,
        outside: inner <= outer,
    })
}

/// How many edges a swallowtail [`cut_swallowtail`] cuts may span.
const SWALLOWTAIL_EDGES: usize = 16;

#[cfg(test)]
mod tests {
    use super::super::{arc_angle, raw::raw_offset_loop};
    use super::*;

    #[test]
    fn swallowtails_cut_as_sweeping_after_every_cut() {
        // Wavy loops shrunk past the waves' curvature: their raw offsets have several
        // swallowtails. Following the first sweep's crossings cuts them as sweeping
        // again after every cut does.
        let mut cut_some = 0;
        for (k, waves) in [7.0, 23.0, 37.0, 53.0].into_iter().enumerate() {
            for delta in [-0.05, -0.1, -0.2, -0.35] {
                let l: Vec<DVec2> = (0..300)
                    .map(|q| {
                        let t = q as f64 / 300.0 * std::f64::consts::TAU;
                        let r = 3.0 + 0.04 * (waves * t).sin() + 0.01 * k as f64 * (3.0 * t).cos();
                        DVec2::from_angle(t) * r
                    })
                    .collect();
                let Some(raw) = raw_offset_loop(&l, delta, arc_angle(delta, 0.01), 0.0005) else {
                    continue;
                };
                let uncut: Shapes = vec![vec![raw]];
                let (mut fast, mut slow) = (uncut.clone(), uncut.clone());
                let (mut fast_cuts, mut slow_cuts) = (Vec::new(), Vec::new());
                let fast_ok = cut_swallowtails(&mut fast, &mut fast_cuts).is_some();
                let slow_ok = cut_swallowtails_by_sweeping(&mut slow, &mut slow_cuts).is_some();
                assert_eq!(fast_ok, slow_ok, "waves {waves} delta {delta}");
                if slow_ok {
                    assert_eq!(fast, slow, "waves {waves} delta {delta}");
                    assert_eq!(fast_cuts, slow_cuts, "waves {waves} delta {delta}");
                    cut_some += usize::from(slow != uncut);
                }
            }
        }
        assert!(cut_some > 0);
    }
}
