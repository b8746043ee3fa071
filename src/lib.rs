//! # edo — equal distance offset planning and printer host for graded-material extrusion
//!
//! edo turns a part and a material-gradient design into equal distance offset (EDO)
//! toolpaths (Xu & Shaw, "SFF-oriented modeling and process planning of functionally
//! graded materials using a novel equal distance offset approach") and drives a
//! multi-syringe slurry extruder over a serial link to build it.
//!
//! The crate is a pure synchronous core, one module per stage, data flowing one way:
//!
//! - [`geom`]: loops and regions (outer boundary Ce, holes Ci), their validation.
//! - [`mesh`]: load a part (STL, 3MF) from bytes within size limits, validate and repair it.
//! - [`slice`]: layer heights (uniform, or adaptive from slope and a Z limit) and the
//!   islands of each layer, in parallel.
//! - [`material`]: compositions, gradient functions f(d), equations (2)–(4), (6), (7).
//!
//! Only the binaries touch files, sockets and clocks.

pub mod cli;
pub mod edo;
pub mod geom;
pub mod job;
pub mod material;
pub mod mesh;
pub mod report;
pub mod slice;
pub mod svg;
