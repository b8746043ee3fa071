//! Which edges a path has and which vertex follows which: the index wrap-around round a
//! closed loop ([`next_in_loop`], [`prev_in_loop`], [`loop_edge`]) and the edges of a loop
//! in order ([`loop_edges`]). Not measures of the path (see `loops.rs`).

use glam::DVec2;

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

/// The edges of a closed loop in order, from vertex 0: `(pts[i], pts[i + 1])`, the last
/// back to the first (without a division per edge).
pub fn loop_edges(pts: &[DVec2]) -> impl Iterator<Item = (DVec2, DVec2)> + '_ {
    let last = pts.last().copied();
    pts.windows(2)
        .map(|w| (w[0], w[1]))
        .chain(last.zip(pts.first().copied()).filter(|_| pts.len() > 1))
}
