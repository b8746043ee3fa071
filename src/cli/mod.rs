//! The command-line front ends' work, kept in the library so the binaries stay thin.
//! These functions do I/O (files, terminal) and so sit outside the pure core.

pub mod client;
pub mod demo;
pub mod gcode;
pub mod linktest;
pub mod linktest_gcode;
pub mod mixer;
pub mod plan;
