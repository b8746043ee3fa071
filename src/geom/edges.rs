//! Which edges a path has and which vertex follows which, for open polylines and closed
//! loops alike: the one definition of a path's edges ([`edges`], and [`edge_ends`] where
//! the vertices' indices are wanted), of a vertex's neighbours along it ([`neighbours`])
//! and of the index wrap-around round a loop ([`next_in_loop`], [`prev_in_loop`]).
//!
//! A path of `n` points has `n − 1` edges open (none for fewer than two points) and `n`
//! closed: edge `k` runs from point `k` to the next, the last of a closed path back to
//! the first (so a closed path of one point has one edge, from it to itself). Not
//! measures of the path (see `loops.rs`).

use glam::DVec2;

/// The edges of the path through `points`, in order: from each point to the next, and
/// from the last back to the first when `closed` (without a division per edge).
pub fn edges(points: &[DVec2], closed: bool) -> impl Iterator<Item = (DVec2, DVec2)> + '_ {
    let closing = if closed {
        points.last().copied().zip(points.first().copied())
    } else {
        None
    };
    points.windows(2).map(|w| (w[0], w[1])).chain(closing)
}

/// The edges of a closed loop in order: [`edges`] closed.
pub fn loop_edges(pts: &[DVec2]) -> impl Iterator<Item = (DVec2, DVec2)> + '_ {
    edges(pts, true)
}

/// How many edges a path of `n` points has.
#[inline]
pub fn edge_count(n: usize, closed: bool) -> usize {
    if closed {
        n
    } else {
        n.saturating_sub(1)
    }
}

/// The edges of a path of `n` points as the indices of their ends, in the order of
/// [`edges`]: `(k, k + 1)`, the last of a closed path `(n − 1, 0)`.
pub fn edge_ends(n: usize, closed: bool) -> impl Iterator<Item = (usize, usize)> {
    (0..edge_count(n, closed)).map(move |k| (k, next_in_loop(k, n)))
}

/// The vertices before and after vertex `k` of a path of `n` points: none before the
/// first or after the last of an open path; round a closed one, the last and the first.
#[inline]
pub fn neighbours(k: usize, n: usize, closed: bool) -> (Option<usize>, Option<usize>) {
    let prev = if k > 0 {
        Some(k - 1)
    } else if closed {
        Some(n - 1)
    } else {
        None
    };
    let next = if k + 1 < n {
        Some(k + 1)
    } else if closed {
        Some(0)
    } else {
        None
    };
    (prev, next)
}

/// The vertex after `k` round a loop of `n` vertices (without an integer division).
#[inline]
pub fn next_in_loop(k: usize, n: usize) -> usize {
    if k + 1 == n {
        0
    } else {
        k + 1
    }
}

/// The vertex before `k` round a loop of `n` vertices.
#[inline]
pub fn prev_in_loop(k: usize, n: usize) -> usize {
    if k == 0 {
        n - 1
    } else {
        k - 1
    }
}

/// Edge `e` of a closed loop: from vertex `e` to the next.
#[inline]
pub fn loop_edge(pts: &[DVec2], e: usize) -> (DVec2, DVec2) {
    (pts[e], pts[next_in_loop(e, pts.len())])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open_and_closed_paths_have_their_edges() {
        let p: Vec<DVec2> = (0..4)
            .map(|k| DVec2::new(k as f64, (k * k) as f64))
            .collect();
        for n in 0..=4 {
            for closed in [false, true] {
                let pts = &p[..n];
                let by_index: Vec<(DVec2, DVec2)> = (0..edge_count(n, closed))
                    .map(|k| (pts[k], pts[(k + 1) % n]))
                    .collect();
                let got: Vec<(DVec2, DVec2)> = edges(pts, closed).collect();
                assert_eq!(got, by_index, "{n} points, closed {closed}");
                let ends: Vec<(DVec2, DVec2)> = edge_ends(n, closed)
                    .map(|(a, b)| (pts[a], pts[b]))
                    .collect();
                assert_eq!(ends, by_index, "{n} points, closed {closed}");
                for k in 0..n {
                    let (prev, next) = neighbours(k, n, closed);
                    assert_eq!(prev, (closed || k > 0).then(|| (k + n - 1) % n));
                    assert_eq!(next, (closed || k + 1 < n).then(|| (k + 1) % n));
                }
            }
        }
    }
}
