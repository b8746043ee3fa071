//! hil-sim: the simulated multi-syringe slurry extrusion machine (see issue "Machine link and hil-sim").
