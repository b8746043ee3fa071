//! The G-code link's marks in the job store: where each connection's line numbers
//! stand in a job's moves. The G-code adapter says what to write
//! ([`GcodeMarkWrite`]); the shell hands it to the store's writer before the next bytes
//! go out, and gives the marks back at the next start ([`super::gcode::ResumeLines`]).

/// Where a G-code connection's line numbers stand in a job's moves, so that after edod's
/// SIGKILL the firmware's last accepted line can be turned back into a move
/// (`docs/firmware.md`, "What edod learns after ...").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GcodeMark {
    /// The job.
    pub job_id: u32,
    /// The line number.
    pub line_number: u32,
    /// The job's move the line comes before.
    pub move_index: u32,
    /// What the line is.
    pub kind: GcodeMarkKind,
}

/// What a [`GcodeMark`]'s line is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GcodeMarkKind {
    /// The first line of a fresh writer (its preamble, then move `move_index` on).
    Writer,
    /// An `M400` sent between the job's moves, before move `move_index`.
    M400,
}

impl GcodeMarkKind {
    /// The name the store keeps it by.
    pub fn as_str(self) -> &'static str {
        match self {
            GcodeMarkKind::Writer => "writer",
            GcodeMarkKind::M400 => "m400",
        }
    }
}

/// A change to the stored [`GcodeMark`]s.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GcodeMarkWrite {
    /// Forget them all: line numbers start again, or the moves after the last mark are
    /// no longer the job's in order (a flush, a reset, a service move).
    Clear,
    /// A fresh writer for a job: replaces every mark.
    Writer(GcodeMark),
    /// Add one.
    Add(GcodeMark),
}
