//! Fault configuration: `--faults key=value,...` and the run-time command language.

pub use edo::link::sim_faults::{FaultParseError, Faults};

/// The `--help` text for `--faults` and run-time commands.
pub const FAULTS_HELP: &str = "\
FAULTS (--faults key=value,...; all off by default):
  corrupt=P       bit-error rate on every data bit, both directions (e.g. 1e-4)
  drop=P          probability a frame (bytes up to a 0x00) is dropped, both directions
  dup=P           probability a frame is delivered twice, both directions
  delay=MS        fixed extra latency, both directions
  jitter=MS       random extra latency 0..MS (byte order is kept, like a real line)
  stall=S         at S seconds stop reading and answering for stall-for (default 3000 ms)
  stall-for=MS    length of a stall
  reset-at=N      reset after N executed moves: boot garbage, new boot id, queue lost
  reset-after=S   reset at S seconds
  unplug-at=S     close the pty at S seconds and open a new one behind --link after
                  unplug-for (default 1000 ms)
  unplug-for=MS   length of an unplug
  empty-at=N      syringe 0 runs empty at executed move N (fault SyringeEmpty)
  limit-at=N      X limit switch trips at executed move N (fault LimitHit)
  estop-at=N      the machine's e-stop button is pressed at executed move N

RUN-TIME COMMANDS (one per line on stdin, unless --no-stdin):
  any fault item above, e.g. `drop=0.05`  change that fault now
  reset | unplug | stall MS | estop | empty N | limit AXIS
  clear           clear all rate faults (corrupt, drop, dup, delay, jitter)
  status          print the machine status as a JSON line on stderr
";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_issue_example() {
        let f = Faults::parse("corrupt=1e-4,drop=0.01,dup=0.001,reset-at=5000").unwrap();
        assert_eq!(f.corrupt, 1e-4);
        assert_eq!(f.drop, 0.01);
        assert_eq!(f.dup, 0.001);
        assert_eq!(f.reset_at_moves, Some(5000));
        assert!(Faults::parse("drop=2").is_err());
        assert!(Faults::parse("nope=1").is_err());
        assert!(Faults::parse("drop").is_err());
        assert_eq!(Faults::parse("").unwrap().stall_for_ms, 3000);
    }
}
