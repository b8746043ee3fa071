//! The binary's options: bad mixer settings are refused before anything starts, naming
//! the option.

use std::process::Command;

#[test]
fn bad_mixer_options_are_refused_naming_the_option() {
    for (args, option) in [
        (&["--mixer", "turbulent"][..], "--mixer:"),
        (&["--mixer", "dispersion"], "--mixer-peclet"),
        (
            &["--mixer", "dispersion", "--mixer-peclet", "0"],
            "--mixer-peclet",
        ),
        (
            &["--mixer", "mixed", "--mixer-peclet", "4"],
            "--mixer-peclet",
        ),
        (
            &["--mixer", "mixed", "--mixer-volume-nl", "NaN"],
            "--mixer-volume-nl",
        ),
        (
            &["--mixer", "mixed", "--mixer-volume-nl=-3"],
            "--mixer-volume-nl",
        ),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
            .args(args)
            .arg("--no-stdin")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} accepted");
        assert!(err.contains(option), "{args:?}: {err}");
        assert!(!String::from_utf8_lossy(&out.stdout).contains("ready"));
    }
}
