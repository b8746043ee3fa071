//! Planning speed of one layer (issue: EDO layer planner): a 2,000-vertex region with
//! two holes, subdivided into m = 20 contours, nozzle 0.4 mm. Target: at most 5 ms per
//! layer on one core.
//!
//! Measured on the 2-core development machine while another build ran (criterion medians
//! of three runs each, back to back): 39.5–44.7 ms, against 43.6–50.0 ms before the
//! planner-speed changes (and 130 ms before the first speed-up). callgrind, one layer:
//! 284M instructions (was 349M). Where they go: i_overlay outlines for the 68 equal
//! distance offsets eq (5) asks for, plus the two boundary offsets, 45 %; the distance
//! field 17 %; level-set extraction 9 %; clipping offsets to their sub-regions 10 %
//! (loops clear of the boundary no longer reach i_overlay); the sub-region differences
//! 4 %; simplification 5 %.
//!
//! 2026-12-01, with the offset end clearance (each sub-region's offsets trimmed
//! `offset_end_clearance_mm` short of the contour they run into) and D_max sampled
//! beside edges: 48.2–53.8 ms (criterion medians of two runs, machine otherwise idle;
//! the same code with the clearance 0: 55.8 ms in a noisier run).
//!
//! 2026-12-01, speed branch: 180M instructions per layer (callgrind), from 300M with
//! the clearance; criterion median 37.0 and 40.8 ms (two runs, machine loaded by another
//! build, load average 3.3 on 2 cores; the old code measured 64.3 ms in the same session
//! at load 2). Alternating runs of a 20-layer driver under the same load: 29–37 ms
//! against 46–66 ms before. What changed: the equal distance offsets no longer go
//! through the i_overlay outline where the raw offset (edges moved, mitred where they
//! meet, round joins where they part, swallowtails cut) is certifiably the offset (no
//! crossing, orientation kept, every vertex at the offset distance from the source);
//! 8 of the 70 offsets still fall back to the outline. Growth-ring offsets are trimmed
//! to the end clearance whole and kept on the sub-region's side of the facing contour,
//! with no clipper. Where the 180M go (inclusive, so nested parts overlap): offsets
//! 27 % (48M: the outline fallback 12M, crossing checks 10M, distance certificate and
//! simplification the rest); the distance field 22 % (39M); level-set extraction 14 %
//! (25M); trimming offsets to the end clearance 14 % (25M); sub-region differences 6 %
//! (12M); the rest is validation, boundary runs, contour clipping and D_max.
//!
//! 2026-12-01, speed2 branch: 134.5M instructions per layer (callgrind, from 180.2M),
//! with the plans byte-identical on this region and the example jobs (every contour
//! and offset vertex the same; sub-region areas within 3e-9 relative, see below).
//! Criterion medians, old and new binaries alternating, machine loaded by another
//! session's build (load average 2.5–3.2 on 2 cores): 44.8 and 43.8 ms before, 36.7
//! and 34.4 ms after; 34.8 ms (33.8–36.1) on the idle machine after the merge. Per stage (inclusive, before -> after): offsets 56.3M -> 44.2M
//! (the outline fallback unchanged at 13.4M, crossing checks 11.1M -> 9.5M); distance
//! field 42.9M -> 29.1M; level-set extraction 27.6M -> 25.6M (chaining 7.6M -> 3.4M)
//! plus simplifying the contours 10.6M -> 9.8M; trimming offsets to the end
//! clearance 29.2M -> 21.4M; sub-region differences 8.9M -> 1.9M; splitting the
//! interior's boundary into hole and outer runs 6.0M less (140.1M -> 134.1M). What
//! changed: `SegmentIndex` keeps its cells in
//! one array, rejects segments by bounding box before the exact distance, and decides
//! `within` on squared distances (the square root only at the rounding edge); grid
//! lookups floor without the libm call; the distance transform relaxes without the
//! equality and NaN tests (they cannot change the result) and reads precomputed node
//! abscissae; level-set segments are linked as the cells are visited instead of
//! through a HashMap; the direct offset's certificate looks at the index once per
//! vertex; the sub-regions between two field (or radial) contours are those nested
//! loops, without the overlay (only that representation changes: the overlay had
//! snapped their areas by up to 3e-9 relative); the boundary runs measure the far
//! boundary only when it comes within the near one's distance. `examples/
//! plan_compare.rs` is the driver and the old/new geometry diff.
//!
//! Why not further: the plan is not stable under a change of the field grid at the
//! 0.01 mm level, so the coarse-grid and banded fields cannot meet "within 0.01 mm of
//! the previous output". Measured with `plan_compare diff` on this region, field cell
//! R_mach/3 against R_mach/3.05 (1.6 % finer): contours move by up to 0.22 mm (C5,
//! whose level d = 0.2 passes next to the saddle of d between the two holes, at d ≈
//! 0.19) and by 0.011–0.073 mm on every other inner contour (medial-axis kinks, cut
//! differently by the grid), and offsets by up to 0.87 mm (ends trimmed where an
//! offset runs nearly parallel to the facing contour at the clearance). The same
//! against R_mach/2: contours 0.059 mm. Tried and not taken (callgrind, per layer):
//! deciding the clearance test for runs of 16 (or 4) offset edges at once, 26.6M ->
//! 28.1M (28.9M) as offsets run within reach of the facing contour almost everywhere;
//! an unstable key sort in `first_crossing`, 9.6M -> 12.8M; sweeping distance
//! transform rows through one mirrored helper, 22.9M -> 39.6M; keeping the swept node
//! in a local, 22.9M -> 30.1M.
//!
//! 2026-12-01, speed3 branch: 123.1M instructions per layer (callgrind, from 133.9M),
//! the plans byte-identical (`plan_compare` JSON of this region and of every
//! `config/examples` job, the femur every 5th layer). Per stage (inclusive, before ->
//! after): trimming offsets to the end clearance 18.2M -> 13.0M (the facing contour's
//! segments near each offset edge are gathered once and answer the edge, split-point
//! and bisection tests; the midpoint pre-test is gone: where it found an edge clear,
//! the edge test does too); offsets 38.1M -> 34.4M, of which crossing checks 7.5M ->
//! 5.7M (neighbour and y tests on precomputed boxes and edge numbers, one pass over
//! the active edges); boundary index builds for the certificates and the facing
//! contours 5.4M -> 4.4M (each contour level's index is built once: the level one
//! sub-region's offsets face is the level the next starts them from); 2.0M more
//! from `SegmentIndex` finding a point's cell by truncation (the same cell, fewer
//! conversions). Trimming ends at 12.5M, offsets at 33.6M.
//! Tried and not taken: carrying a lower bound on the distance to the facing contour
//! along each offset (bounded nearest-distance lookups at vertices, an edge clear
//! when the bound less its length stays above the clearance), 18.2M -> 20.2M with
//! the bound radius 2 x the clearance (22.1M at 8 x): offset edges (about 1 mm) are
//! long against the 0.2 mm clearance and most pass within reach of the contour, so the
//! lookups decided only 43 % of the edges. Answering the offset certificate for runs
//! of raw vertices close together (the two ends at a vertex the offset parts from)
//! from segments gathered once per run: 125.1M -> 125.3M per layer (runs up to a
//! quarter of the offset distance across; 125.2M up to the whole distance), the
//! distance tests 6.3M -> 3.7M but the gathering cost more than it saved.
//!
//! 2026-12-01, exact level sets (field.rs steps 6-7) merged with speed3: 96.7M
//! instructions per layer (callgrind, from 134.5M at the start of the day's last
//! session); criterion median 17.6 ms (17.3-18.0), machine idle, from 34.8 ms. The
//! field cell went from R_mach / 3 to R_mach / 2, with every crossing of a cell side
//! placed on the exact level set and the corners where level sets cross the medial
//! axis added; the plans changed, and are judged against the exact level sets
//! (`plan_compare levels`) rather than against the previous grid: mean distance on
//! this region 0.0029 mm (was 0.0032), 99.9th percentile 0.012 mm (was 0.023);
//! femur every 5th layer 99th percentile 0.021 mm (was 0.042), 99.9th 0.041 mm (was
//! 0.127). Where the 96.7M go (inclusive): offsets 25.1M; level sets 26.2M, of which
//! placing crossings on the exact level sets 14M (exact distances 10.2M); trimming
//! offsets to the end clearance 12.3M; the two distance transforms 11.7M;
//! simplification 7.5M. Tried: cell R_mach / 1.5 (106M with the corners found only
//! from the midpoint) rounds off the tips of level sets on the femur (99.9th
//! percentile 0.23 mm), so the cell stays at R_mach / 2.
//!
//! The 5 ms target (about 20M instructions at this machine's rate) is still out of
//! reach: the offsets alone (68 equal distance offsets and the two boundary
//! offsets; 3 of the 70 now need the i_overlay outline, 5.0M) take 25M, and the level
//! sets, the distance transforms and the trimming another 50M. cavalier_contours 0.9 parallel_offset was measured too (offsets
//! 132M -> 54.5M) and not taken: a debug assertion in it fails on an example job (a
//! 0.06 mm sliver eroded by 0.4 mm) and its offset path has expect()s.
//!
//! 2026-12-01, off4 branch (equal distance offsets): 92.6M instructions per layer
//! (callgrind, from 96.9M), the plans byte-identical (`plan_compare` JSON of this
//! region, of paper-annulus, tooth-crown, fibers and non-star, and of the femur every
//! 5th layer). Per stage (inclusive, before -> after): offsets 25.1M -> 24.0M, of which
//! crossing checks 4.8M -> 4.3M; trimming offsets to the end clearance 12.5M -> 9.8M;
//! boundary index builds 3.8M -> 3.4M (the three together 41.5M -> 37.2M). What
//! changed: the trimming gathers the facing contour's segments once per window (a run
//! of consecutive road edges at most 8 clearances across) and answers every edge's
//! clear test, split points and bisections in it from them, builds the per-point lists
//! only for roads that come near, and rejects a segment lying wholly beyond the reach
//! on one side of the edge's line before the exact segment distance; first_crossing
//! sorts its sweep keys as the integers `total_cmp` compares (the same stable order);
//! `SegmentIndex` finds cells through an i64 truncation; a join turning surely less
//! than one arc step is one piece without the arc tangent; spikes and duplicate points
//! are told apart without square roots where they clearly are not. Tried and not taken
//! (per layer): the windows 4 and 16 clearances across, 10.5M and 9.9M; gathering the
//! certificate's source segments per window of raw vertices 4 and 8 offset distances
//! across, offsets 24.0M -> 24.0M and 24.3M; certificate indices with cells twice the
//! offset distance instead of twice the mean segment (0.85 mm against 1.7 mm),
//! certificate queries 5.8M -> 6.1M and index builds 1.2M more; a bucket sort for the
//! crossing sweep, 4.8M -> 6.4M; a slimmer tagged segment there, 4.8M -> 5.3M; each
//! segment's box kept in `SegmentIndex` with the box test in plain comparisons,
//! certificate queries 5.8M -> 6.3M; the whole edge taken as near when both its ends
//! lie inside one contour segment's clearance, 0.04M less (not worth the code). The 3
//! offsets that fall back to the outline (5.0M) fail the distance certificate, not the
//! crossing check: the outline is needed there. Emitting fewer round-join vertices was
//! not tried: simplification removes only 1.6k of the 12.8k raw vertices per layer.
//!
//! 2026-12-01, fifth session, merged with off4: 85.1M instructions per layer
//! (callgrind, from 96.8M at the session's start). Criterion medians, the session's
//! start (c38716a) and this code alternating on the idle machine: 26.1 and 26.2 ms
//! before, 22.5 and 22.4 ms after (-14 %). The machine ran about 45 % slower than in
//! the session that measured 17.6 ms for c38716a, so only same-session figures
//! compare. Mine (the field, level sets and shapes): contour levels become shapes
//! without the overlay where their loops already are a valid even-odd set (no
//! crossing, none degenerate; oriented and nested directly), 96.8M -> 92.6M; the hot
//! loops lost their divisions (each boundary edge keeps 1/|ab|², the walk round a
//! loop steps without an integer modulo, loop edges without `% n`, Douglas-Peucker on
//! squared distances), 1.1M fewer instructions but more time than that (level sets
//! 5.5 -> 4.75 ms in one instrumented run); marching reads floor(d m) per node once,
//! 1.6M. Per stage now (instrumented run, per layer, slow machine): distance
//! transforms 2.8 ms, level sets 4.75 ms, simplification and shapes 1.0 ms, boundary
//! offsets 0.44 ms, boundary runs and contour roads 0.5 ms, sub-regions and D_max 1.6
//! ms, equal distance offsets 6.8 ms, trimming 4.2 ms (the last two before off4).
//! Tried and not taken: Newton's second step seeded from the edges its first found
//! (with the other local minimum kept where it can have become the nearer), 96.8M ->
//! 97.3M: the nodes' seeds already lie a step or two from the nearest edge; the
//! distance transform relaxing from the row before first and the node before last
//! (shorter dependency chain along a row), no change in time.
//!
//! Why 5 ms stays out of reach with this design: the layer's 85M instructions come
//! to about 9,000 per road vertex (about 9,500 a layer), spent on an exact
//! nearest-point walk per placed contour point, a certified equal distance offset per
//! offset vertex and a clearance test per offset edge. The target needs 4.5 times
//! less time on this session's machine (3.5 at the earlier session's speed). Tuning
//! took the layer from 134.5M to 85.1M over the day, and each step left is worth
//! 1-3 %. Getting there takes a different method, not tuning: for example offsets
//! taken as level sets of a per-band distance to their own contour (no certificate,
//! crossing check, outline fallback or index builds), or contour crossings placed by
//! Hermite interpolation between node distances and gradients made exact by one walk
//! per node beside a crossing, with Newton steps only where a side crosses the
//! medial axis.
//!
//! 2026-12-01, off5 branch (equal distance offsets): 78.2M instructions per layer
//! (callgrind, from 85.1M); offsets 24.55M -> 18.77M, trimming 9.83M -> 9.50M. What
//! changed: the offsets are simplified in one greedy pass (`simplify_loop_greedy`, the
//! same guarantee as Douglas-Peucker: every dropped vertex within chord/20 of its
//! chord), 4.1M -> 0.78M, where Douglas-Peucker kept 87 % of the vertices and so ran at
//! its worst case (85.1M -> 81.8M); swallowtails are cut from one sweep that finds every
//! crossing pair, the pairs left after a cut followed without sweeping again (plans
//! identical; crossing checks 5.75M -> 4.95M, 81.8M -> 81.3M); a round join whose arc
//! midpoint lies within chord/20 of both moved edges is that one point, which removes
//! about 2,500 raw vertices a layer before the certificate, the crossing check and the
//! trimming (81.3M -> 78.2M). The plans move within the tolerance compounded over the
//! successive offsets (bench 0.001 mm away from offset ends; femur every 5th layer
//! 0.01 mm, and its contours up to 0.009 mm through the boundary offsets), and ends
//! trimmed at the clearance where an offset runs nearly parallel to the facing contour
//! by up to 0.15 mm on the bench and 0.76 mm on the femur. Coverage (toolpath_report,
//! void / overlap %, before -> after): paper-annulus 0.010 / 0.010 -> 0.009 / 0.011;
//! tooth-crown 0.177 / 0.587 -> 0.175 / 0.560; non-star 0.443 / 1.596 -> 0.479 /
//! 1.619; Benchy 0.421 / 1.340 -> 0.433 / 1.302; femur 0.174 / 0.646 -> 0.177 / 0.645.
//!
//! 2026-12-01, sixth session, merged with off5: 69.2M instructions per layer (callgrind,
//! from 85.1M at the session's start). Criterion medians, the session's start (3c97c76)
//! and this code alternating on the idle machine: 12.0 and 12.7 ms before, 9.4 and 10.2
//! ms after (-21 %); this session's machine ran about twice as fast as the last one's,
//! so only same-session figures compare. Mine (the field, level sets and sub-regions):
//! level sets march one piece per cell and level from a 32-case table built at compile
//! time from the cell's four triangles (same crossings, same joins, same loop starts:
//! plans byte-identical), level sets 21.9M -> 18.5M; a first Newton step under 0.01 mm
//! where both nodes' walks find the same nearest points is not checked by a second
//! (level-set accuracy unchanged: bench mean 0.00294 mm, p99.9 0.0120), 81.8M -> 78.0M;
//! the sub-regions next to the boundary offsets are their levels' loops without the
//! overlay where no lower edge comes within a chord of the upper level (roads
//! identical), 1.1M; level sets reserve their pieces and loops, 1.0M. Tried and not
//! taken: a 4-neighbour distance transform (6 relaxations a node instead of 10),
//! distance transforms 11.6M -> 8.6M but 80.3M in all (worse seeds cost the walks) and
//! the level sets less exact (bench p99.9 0.0120 -> 0.0145 mm, femur 0.041 -> 0.057,
//! six structural differences on the femur). Where the 69.2M go now (inclusive):
//! offsets 18.8M, distance field 13.5M (transforms 11.6M), level sets 13.7M (exact
//! distances 5.5M), trimming 9.5M, boundary index builds 3.3M. The 5 ms target needs
//! about 2 times less on this session's machine.
//!
//! 2026-12-02, off6 branch (the equal distance offsets' outline fallback): 64.3M
//! instructions per layer (callgrind, from 69.2M); offsets (`offset_indexed`, inclusive)
//! 18.7M -> 13.9M. None of the bench layer's 70 offsets falls back to the i_overlay
//! outline now (3 did, 1.7M each; the 2 left are in the bench's probe plan: a neck that
//! pinches off, an island that splits away). What changed in the direct offset: a loop
//! the offset swallows whole (an outer loop shrunk or a hole grown past its width: its
//! box narrower than twice the step, or less area than the step's disk; the bench
//! layer's 18 x 2 um sliver) is dropped; a swallowtail's cut point is certified up to
//! chord/20 nearer than the step (it lies on chords of merged joins, up to that much
//! inside their arcs: the 5.7e-7 mm misses were these, not rounding; raw vertices keep
//! the relative 1e-9); a raw vertex the certificate rejects that is the apex of a spike
//! (a reversed micro-edge backing up along the edge before it, so that the
//! swallowtail's edges just miss each other: 2 to 19 um near) is cut off where the
//! line of one edge crosses the other, that point certified as a cut point and the
//! crossings and orientations checked again. Plans: bench within 0.0008 mm, the example
//! jobs identical; on the femur (every 5th layer) 2,009 more offsets go direct, as
//! close to the outline as those direct before (median 0.0004 mm, p99 0.009 mm: round
//! joins sampled another way), roads within 0.011 mm of the old ones away from their
//! ends, and ends trimmed where an offset runs nearly along the facing contour move by
//! up to 0.51 mm (3.3 mm of 235,000 mm of offsets beyond 0.01 mm). Not taken: cutting
//! such spikes in every raw loop before the certificate (a pass over every offset for
//! three a layer, and it could cut a spike that is on the offset; cutting only at a
//! vertex the certificate rejects cannot); an absolute slack for every raw vertex (they
//! are exact up to rounding; only cut points lie on chords).
//!
//! 2026-12-02, seventh session, merged with off6: 62.1M instructions per layer
//! (callgrind, from 69.2M at the session's start). Criterion medians, the session's
//! start (822d41e) and this code alternating: 9.57, 10.32 and 9.63 ms before, 8.78,
//! 8.63 and 8.74 ms after (-10 %). Mine, plans byte-identical: the distance transforms
//! sweep each row only over its stretch of the convex hull of Ce (25.6k of the 35.2k
//! nodes here), 11.55M -> 9.9M; D_max's samples try the segment that answered the
//! previous one first, 0.7M. The field's grid buffers are kept per thread between
//! layers (`field::pool`): freed at the end of each layer, they let glibc hand the
//! pages back and fault them in again for the next, 575 page faults a layer and about
//! 12 % of the time where layers are planned one after another on one thread (as the
//! daemon does while streaming; 201 plans of `plan_compare bench` 1.68 -> 1.54 s).
//! Under criterion the heap happened to stay grown (3,023 faults in all before), so
//! there the gain is only the instructions'. Tried and not taken: relaxing the
//! transforms without a branch (bit-mask selects), 201 plans 1.8-2.3 s -> 2.3-2.7 s;
//! the contours simplified by the greedy pass the offsets use instead of
//! Douglas-Peucker, 1.4M fewer in all but the coarser contours make the offsets fall
//! back to the outline more often (offsets 18.8M -> 20.2M) and move offset ends by up
//! to 3.8 mm; each offset taken from the contour at i steps instead of one step from
//! the previous offset (every certificate on the contour's index), 76.3M (more
//! fallbacks); `SegmentIndex` finding cells by a multiplication instead of a division,
//! and keeping each segment's 1 / |ab|² for the point queries, no time change beyond
//! the noise (criterion 7.68 and 8.23 ms against 7.52 and 8.21 ms); `exact_at` with
//! three divisions instead of seven (plans then differ by rounding, up to 0.00007 mm),
//! no time change beyond the noise. Where the 62.1M go now (inclusive): level sets
//! 13.9M (exact distances 5.5M), offsets 13.8M, distance field 11.9M (transforms
//! 9.9M), trimming 9.5M, the rest (validation, boundary offsets and runs, D_max,
//! contour simplification, index builds) about 13M. The 5 ms target needs about 1.75
//! times less on this session's machine.
//!
//! 2026-12-02, eighth session: 54.5M instructions per layer (callgrind, from 62.3M).
//! The inner contours are simplified at the new contour deviation (`process.
//! contour_deviation`, default 0.025 mm, Cura's default maximum deviation) instead of
//! the 0.01 mm chord tolerance; every offset is made from a contour and its work grows
//! with the contour's vertex count: offsets 13.35M -> 8.9M, trimming 9.45M -> 8.0M.
//! Criterion medians, the session's start (b99b698) and this code alternating, three
//! runs each, on a machine slower than earlier the same day: 9.05, 9.48 and 8.79 ms
//! before, 7.85, 8.18 and 7.26 ms after; the second bench (contours at 0.01 mm, as
//! before) 8.72, 8.62 and 9.28 ms. Earlier in the session, quieter, one run of this
//! code: 6.29 ms. Level-set accuracy (`plan_compare levels`) is now the deviation's:
//! bench mean 0.0074 mm, p99.9 0.026 mm; coverage in docs/toolpath.md. Tried and not
//! taken: the outline too at 0.025 mm, 51.4M but more void along the part's surface
//! (annulus 0.009 -> 0.019 %, Benchy 0.434 -> 0.486 %); the field cell R_mach / 1.5
//! instead of R_mach / 2, 47.6M but the femur's level sets worse at the tail (p99.9
//! 0.043 -> 0.081 mm, corners of the level sets cut at the medial axis, 0.071 mm with
//! three bend refinements instead of one) and two offsets falling back to the
//! outline; looking for such a corner's tip across the chord instead of by Newton
//! steps from its middle, worse (femur p99.9 0.064 mm even at R_mach / 2); 4-neighbour
//! transforms, 1.6M fewer but femur p99.9 0.041 -> 0.057 mm; both transforms in one sweep
//! (plans identical), 54.8M and no time change; the row sweeps split into a
//! below-neighbour pass and the sequential passes (plans identical), no time change;
//! fat LTO and one codegen unit, 0.9M more and no time change (201 plans 1.56-1.64
//! s either way); the offsets' own simplification at chord / 5 or chord / 2 instead of
//! chord / 20, no gain (their vertices are not micro-edges); Newton's trust step and
//! the bend threshold raised to the contour deviation's scale, 0.2M.
//!
//! 2026-12-02, ninth session: 50.7M instructions per layer (callgrind, from 54.5M).
//! The level-set trace places every other crossing round a loop first and leaves out
//! one between two that lie on the level set where the exact normals turn so little
//! that the straight piece joining them strays at most half the contour deviation
//! (chord × turn / 4): 13,428 crossings placed before, 8,022 after; the rest of
//! the plan follows from fewer contour vertices. Level-set accuracy: bench mean
//! 0.0074 -> 0.0077 mm, p99.9 0.026 -> 0.027 mm, largest 0.032 mm unchanged; femur
//! every 5th layer p99.9 0.043 mm and largest 0.37 mm unchanged. Criterion medians,
//! the session's start (fc19b95) and this code alternating, three runs each, machine
//! busier than at the session's start (when fc19b95 alone measured 6.55 ms): 8.26,
//! 9.01 and 8.09 ms before, 8.00, 8.13 and 7.43 ms after. Tried and not taken: a
//! quarter of the deviation instead of half, 51.6M; placing every 4th crossing first
//! and halving stretches that are not straight, 49.7M but the femur's p99.9 0.043 ->
//! 0.056 mm (a corner between two crossings four apart whose normals agree is lost);
//! each offset from the contour at i steps on the contour's index (again, now that
//! contours are coarser), 51.5M (more outline fallbacks); the transform's nearest
//! points as columns so the three relaxations from the row before vectorise (plans
//! identical): 11.8M for the transforms against 9.95M, since without AVX the selects
//! cost more than the branches they replace (with AVX2 for the whole build, 9.8M:
//! not worth a second code path chosen at run time).
//!
//! 2026-12-02, tenth session: 48.75M instructions per layer (callgrind, from 50.66M),
//! the plans byte-identical (this region, every `config/examples` job, the femur every
//! 5th layer). The level sets march only the cells with a corner inside Ce (per row,
//! from the first node with floor(d m) below m to the last), on i32 bands floored
//! without a branch, 10.97M -> 10.13M; the interior's boundary is split into hole and
//! outer runs by two bounded looks (only one boundary within the boundary offset
//! decides) before measuring distances, 0.37M; the trimming's gathering takes each
//! segment once by a per-segment stamp instead of scanning those already taken, and
//! the growth-ring offsets are kept on their side of the facing contour by crossings of
//! a ray in the cells of its index instead of a point-in-loop pass over every loop
//! (trimming 8.00M -> 7.68M, and the side test 0.28M less). Wall time: the session's start (f6aa34f) and this code
//! alternating, criterion medians 7.05, 6.90 and 6.25 ms before, 6.83, 7.02 and 6.37
//! ms after; 150 plans of `plan_compare bench`, eight alternations each, median
//! 7.10 ms before and 7.04 ms after a plan: within the noise of a machine whose speed
//! moved by 10 % from one minute to the next (one earlier criterion run of the old
//! code, quiet: 6.16 ms). Tried and not taken: each split point and bisection of the
//! trimming trying first the segment that answered the edge (49.03M -> 49.70M: the
//! first segment in the window mostly answers anyway, and far points pay for the
//! extra test); the transforms without the sideways passes along each row (8
//! relaxations a node instead of 10), 78.2M, as the worse seeds lengthen the walks,
//! and the femur's p99.9 0.043 -> 0.152 mm. Where the 48.75M go (inclusive): distance
//! field 12.0M (transforms 9.95M), level sets 10.1M (placement 4.7M), offsets 9.3M,
//! trimming 7.7M, the rest about 9.6M. The 5 ms target needs about 1.25 times less at
//! this session's quietest (6.16 ms for the old code).
//!
//! 2026-12-02, eleventh session: 48.73M instructions per layer, the plan of this
//! region and of every `config/examples` job but the femur byte-identical. The corner
//! search between two crossings now starts only where their tangents meet ahead of one
//! and behind the other (across an S-bend they met beyond both, and the placed point
//! made the contour double back: on every 5th femur layer, 25 vertices turning back
//! by more than 120 degrees beside an edge under 0.2 mm before, 5 after; test
//! `femur_contours_have_no_spikes`); femur level-set p99.9 0.043 -> 0.042 mm.
//! Criterion median 6.81 ms at the session's start on the idle machine; 100 plans of
//! `plan_compare bench`, ten runs back to back: 5.67 to 7.49 ms a plan. Tried and
//! not taken: a coarser field made as exact by bending more. With pieces also bent
//! where chord x turn / 4 exceeds the sparse share of the deviation (the rule the
//! left-out crossings keep), R_mach / 1.5 still gave the femur p99 0.028 mm (over the
//! 0.025 mm deviation) at one bend a piece, and 0.024 mm at up to three (p99.9 0.071
//! mm) but then 50.1M a layer here, more than at R_mach / 2: the bends cost more than
//! the coarser grid saves. At R_mach / 2 the same rule gives the femur p99 0.024 and
//! p99.9 0.041 mm for 0.5M more a layer (not taken: the target is speed). mimalloc
//! as the allocator: 48.08M, wall time within the noise (not worth a dependency).
//!
//! 2026-12-03, twelfth session: 48.73M instructions per layer, unchanged (the plan of
//! this region byte-identical). Criterion median 7.10 ms at the session's start, 9.34 ms
//! later on the same code while the machine was slower (load average about 1 with
//! nothing else of ours running); `perf` self time: the distance transform 16.6 %,
//! trimming offsets to the end clearance 10 %, `within_both` 6.4 %, marching the
//! level sets 6.2 %, allocation about 5 %. Tried and not taken: the distance
//! transform on a grid twice as coarse, each node then taking the exact distance to
//! the edges nearest its (up to four) coarse neighbours: the transforms 10.5M ->
//! 8.1M, but 1.0M a layer saved in all (one offset more falls back to the outline), the
//! femur's level sets worse at the tail (every 5th layer p99.9 0.042 -> 0.052 mm; bench
//! largest 0.032 -> 0.034 mm), and no better with the edges of the node's left and
//! lower neighbours offered too (53.5M); four times as coarse, 58.0M and the bench
//! largest 0.10 mm; keeping each node's best in a local through the sweeps, 49.35M;
//! `target-cpu=native`, about 5 % of wall time at best and not portable. The 5 ms
//! target needs about 1.3 to 1.8 times less than this machine's medians: a method
//! change (the fifth session's note names two), not tuning.
//!
//! 2026-12-04, thirteenth session: the same code (48.99M instructions per layer by
//! callgrind, 11 plans less 1 of `plan_compare bench`; the earlier 48.73M counted one
//! layer inside criterion's loop) measured on this session's machine, idle (load
//! average 0.0-0.5, AMD EPYC at 2.6 GHz): criterion medians 4.26, 4.40 and 4.45 ms in
//! three runs back to back (intervals 4.26-4.27, 4.38-4.41, 4.44-4.47 ms), under the
//! 5 ms target; the contours at 0.01 mm 5.20, 5.31 and 5.34 ms. 201 plans of
//! `plan_compare bench` 0.97-1.01 s, against 1.54-1.68 s for the same count in the
//! seventh to tenth sessions: this machine runs about 1.6 times faster than theirs,
//! and on theirs the same instructions took 6.2-9.3 ms. The figure therefore holds on
//! a machine of today's speed; on the slower machines of the earlier sessions it is
//! 1.25-1.9 times over, and a method change (the fifth session's note) is what would
//! bring it under there too.

use criterion::{criterion_group, criterion_main, Criterion};
use edo::plan::{plan_region, PlanOptions};
use std::hint::black_box;

#[path = "common/region.rs"]
mod region;
use region::{bench_design, bench_region};

fn bench(c: &mut Criterion) {
    let region = bench_region();
    let design = bench_design();
    // Choose R_mach so that eq (1) gives m = 20 for this region's L_short.
    let probe = plan_region(&region, 0, &design, &PlanOptions::new(1.0, 0.4)).unwrap();
    let opts = PlanOptions::new(probe.l_short_mm / 20.0, 0.4);
    let plan = plan_region(&region, 0, &design, &opts).unwrap();
    assert_eq!(plan.m, 20);
    eprintln!(
        "bench region: {:?} subdivision, m = {}, {} sub-regions, {} offsets",
        plan.method,
        plan.m,
        plan.sub_regions.len(),
        plan.sub_regions
            .iter()
            .map(|s| s.offsets.len())
            .sum::<usize>()
    );
    c.bench_function("plan_layer_2000v_2holes_m20", |b| {
        b.iter(|| plan_region(black_box(&region), 0, &design, &opts).unwrap())
    });
    // The same with the inner contours simplified at the 0.01 mm chord tolerance
    // instead of the default contour deviation (0.025 mm).
    let fine = PlanOptions {
        contour_deviation_mm: 0.01,
        ..opts.clone()
    };
    c.bench_function("plan_layer_2000v_2holes_m20_contours_0.01mm", |b| {
        b.iter(|| plan_region(black_box(&region), 0, &design, &fine).unwrap())
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
