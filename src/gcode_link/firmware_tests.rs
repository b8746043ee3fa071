//! Unit tests of the firmware models: each rule of the module docs, and the cases the
//! checksum does not catch (`docs/firmware.md`).

use super::*;
use crate::gcode_link::numbered_line;

fn t(ms: u64) -> Micros {
    Micros(ms * 1000)
}

fn model(dialect: Dialect, tweak: impl FnOnce(&mut FirmwareConfig)) -> Firmware {
    let mut cfg = FirmwareConfig::for_dialect(dialect);
    cfg.loop_period_us = 0;
    tweak(&mut cfg);
    let mut fw = Firmware::new(cfg, t(0));
    replies(&mut fw); // the boot banner
    fw
}

fn replies(fw: &mut Firmware) -> Vec<String> {
    std::iter::from_fn(|| fw.poll_transmit())
        .map(|b| {
            String::from_utf8_lossy(&b)
                .trim_end_matches('\n')
                .to_string()
        })
        .collect()
}

fn lines(fw: &mut Firmware) -> Vec<(Option<u32>, String)> {
    std::iter::from_fn(|| fw.poll_line())
        .map(|l| (l.line_number, l.text))
        .collect()
}

fn send(fw: &mut Firmware, n: u32, text: &str, now: Micros) {
    fw.handle_bytes(&numbered_line(n, text), now);
}

fn handshake(fw: &mut Firmware) {
    fw.handle_bytes(&numbered_line(0, "M110 N0"), t(0));
    assert_eq!(replies(fw), vec!["ok"]);
    lines(fw);
}

#[test]
fn marlin_boots_with_start_and_the_reset_reason() {
    let mut fw = Firmware::new(FirmwareConfig::for_dialect(Dialect::Marlin), t(0));
    let r = replies(&mut fw);
    assert_eq!(&r[..2], ["start", "PowerUp"]);
    fw.reset(t(1));
    assert_eq!(&replies(&mut fw)[..2], ["start", " External Reset"]);
}

#[test]
fn marlin_accepts_the_next_line_number_with_its_checksum() {
    let mut fw = model(Dialect::Marlin, |_| {});
    handshake(&mut fw);
    send(&mut fw, 1, "G1 X1", t(1));
    send(&mut fw, 2, "M115", t(1));
    let r = replies(&mut fw);
    assert_eq!(r[0], "ok");
    assert!(r[1].starts_with("FIRMWARE_NAME:Marlin"));
    assert_eq!(r.last().map(String::as_str), Some("ok"));
    assert_eq!(
        lines(&mut fw),
        vec![(Some(1), "G1 X1".into()), (Some(2), "M115".into())]
    );
    assert_eq!(fw.last_line_number(), 2);
}

#[test]
fn marlin_line_errors_answer_error_resend_ok() {
    let mut fw = model(Dialect::Marlin, |_| {});
    handshake(&mut fw);
    send(&mut fw, 2, "G1 X1", t(1));
    assert_eq!(
        replies(&mut fw),
        vec![
            format!("Error:{LINE_NUMBER_ERROR}0"),
            "Resend: 1".into(),
            "ok".into()
        ]
    );
    fw.handle_bytes(b"N1 G1 X1*99\n", t(2));
    assert_eq!(
        replies(&mut fw),
        vec![
            format!("Error:{CHECKSUM_ERROR}0"),
            "Resend: 1".into(),
            "ok".into()
        ]
    );
    fw.handle_bytes(b"N1 G1 X1\n", t(3));
    assert_eq!(
        replies(&mut fw),
        vec![
            format!("Error:{NO_CHECKSUM_ERROR}0"),
            "Resend: 1".into(),
            "ok".into()
        ]
    );
    assert!(lines(&mut fw).is_empty());
    assert_eq!(fw.stats().line_errors, 3);
}

#[test]
fn marlin_runs_unnumbered_lines_unchecked() {
    let mut fw = model(Dialect::Marlin, |_| {});
    fw.handle_bytes(b"G1 X5*77\n", t(1));
    assert_eq!(replies(&mut fw), vec!["ok"]);
    assert_eq!(lines(&mut fw), vec![(None, "G1 X5*77".into())]);
}

#[test]
fn marlin_numbered_m110_sets_the_line_number_when_read() {
    let mut fw = model(Dialect::Marlin, |_| {});
    send(&mut fw, 1, "G1 X1", t(1));
    fw.handle_bytes(&numbered_line(77, "M110 N40"), t(2));
    send(&mut fw, 41, "G1 X2", t(3));
    assert_eq!(replies(&mut fw), vec!["ok", "ok", "ok"]);
    assert_eq!(fw.last_line_number(), 41);
}

#[test]
fn marlin_drain_turns_the_tail_of_the_next_line_into_an_unchecked_line() {
    let mut fw = model(Dialect::Marlin, |c| c.loop_period_us = 1000);
    handshake(&mut fw);
    // A bad line 1 and the first bytes of line 2 are in the buffer when the main loop
    // reads them; the rest of line 2 arrives after the drain.
    let next = numbered_line(2, "G1 X10 Y20");
    let (head, tail) = next.split_at(5);
    let mut bytes = b"N1 G1 X1*0\n".to_vec();
    bytes.extend_from_slice(head);
    fw.handle_bytes(&bytes, Micros(1_000_100));
    fw.handle_timeout(Micros(2_000_000));
    assert_eq!(replies(&mut fw)[1], "Resend: 1");
    assert_eq!(fw.stats().bytes_drained, 5);
    fw.handle_bytes(tail, Micros(2_000_100));
    fw.handle_timeout(Micros(3_000_000));
    let got = lines(&mut fw);
    assert_eq!(got.len(), 1);
    assert!(
        got[0].0.is_none() && got[0].1.starts_with("X10 Y20*"),
        "{got:?}"
    );
}

#[test]
fn marlin_advanced_ok_echoes_n_and_under_reports_free_slots_by_one() {
    let mut fw = model(Dialect::Marlin, |c| c.advanced_ok = true);
    fw.handle_bytes(&numbered_line(0, "M110 N0"), t(0));
    // The queue is empty but for the acknowledged line: B = BUFSIZE − 1.
    assert_eq!(replies(&mut fw), vec!["ok N0 P16 B3"]);
    send(&mut fw, 1, "G1 X1", t(1));
    assert_eq!(replies(&mut fw), vec!["ok N1 P15 B3"]);
    fw.handle_bytes(b"M114\n", t(2));
    assert_eq!(replies(&mut fw), vec!["ok P15 B3"]);
}

#[test]
fn marlin_stops_reading_while_the_planner_is_full_and_keeps_alive() {
    let mut fw = model(Dialect::Marlin, |c| c.planner_blocks = 2);
    handshake(&mut fw);
    for n in 1..=8 {
        send(&mut fw, n, &format!("G1 X{n}"), t(1));
    }
    // Two moves planned, the third blocks in its handler: the lines after it wait in the
    // receive buffer (no reading while a handler blocks); no ok until a move is done.
    assert_eq!(replies(&mut fw), vec!["ok", "ok"]);
    assert_eq!(fw.queue_len(), 1);
    assert!(fw.rx_len() > 0);
    let k = fw.next_timeout().unwrap();
    assert_eq!(k, t(2001));
    fw.handle_timeout(k);
    assert_eq!(replies(&mut fw), vec!["echo:busy: processing"]);
    fw.moves_done(2, t(2500));
    assert_eq!(replies(&mut fw), vec!["ok", "ok"]);
    assert_eq!(lines(&mut fw).len(), 4);
    // Each pass read before it processed: 5, 6, 7 queued, 8 waits behind the blocked 5.
    assert_eq!(fw.queue_len(), 3);
    assert_eq!(fw.rx_len(), numbered_line(8, "G1 X8").len());
}

#[test]
fn marlin_drops_bytes_past_a_full_uart_buffer() {
    let mut fw = model(Dialect::Marlin, |c| c.planner_blocks = 0);
    handshake(&mut fw);
    send(&mut fw, 1, "G1 X1", t(1)); // blocks: no planner space, no reading
    let mut bytes = Vec::new();
    for n in 2..=10 {
        bytes.extend_from_slice(&numbered_line(n, "G1 X100.000 Y100.000 E0.12345 F1800"));
    }
    fw.handle_bytes(&bytes, t(1));
    assert!(fw.stats().bytes_dropped > 0);
    assert_eq!(fw.rx_len(), 128);
}

#[test]
fn marlin_m112_waits_behind_a_blocked_queue_without_the_emergency_parser() {
    for ep in [false, true] {
        let mut fw = model(Dialect::Marlin, |c| {
            c.planner_blocks = 0;
            c.emergency_parser = ep;
        });
        handshake(&mut fw);
        send(&mut fw, 1, "G1 X1", t(1)); // blocks: no planner space
        fw.handle_bytes(b"\nM112\n", t(2));
        assert_eq!(fw.is_halted(), ep, "emergency parser {ep}");
        if ep {
            assert_eq!(
                replies(&mut fw),
                vec!["Error:Printer halted. kill() called!"]
            );
        }
    }
    let mut fw = model(Dialect::Marlin, |c| c.emergency_parser = true);
    fw.handle_bytes(&numbered_line(9, "M112"), t(1));
    assert!(fw.is_halted(), "N<n> M112*<cs> counts too");
}

#[test]
fn marlin_spurious_resend_rejects_a_good_line() {
    let mut fw = model(Dialect::Marlin, |_| {});
    handshake(&mut fw);
    fw.inject_spurious_resend();
    send(&mut fw, 1, "G1 X1", t(1));
    assert_eq!(replies(&mut fw)[1], "Resend: 1");
    send(&mut fw, 1, "G1 X1", t(2));
    assert_eq!(replies(&mut fw), vec!["ok"]);
}

#[test]
fn marlin_hole_a_corrupted_leading_n_runs_the_line_unchecked() {
    let mut fw = model(Dialect::Marlin, |_| {});
    handshake(&mut fw);
    let mut bytes = numbered_line(1, "G1 X1");
    bytes[0] = b'G'; // `N1 G1 X1*..` becomes `G1 G1 X1*..`
    fw.handle_bytes(&bytes, t(1));
    assert_eq!(replies(&mut fw), vec!["ok"]);
    assert_eq!(lines(&mut fw).len(), 1);
    assert_eq!(fw.last_line_number(), 0);
}

#[test]
fn marlin_hole_a_lost_line_end_can_merge_two_lines_under_one_checksum() {
    let mut fw = model(Dialect::Marlin, |_| {});
    handshake(&mut fw);
    let first = numbered_line(1, "G1 X1");
    let second = numbered_line(2, "G1 X2");
    // The newline of line 1 turned into the one byte that keeps the XOR right.
    let x = checksum(&first[..first.len() - 1]);
    assert!(!matches!(x, b'\n' | b'\r' | b';' | 0));
    let mut bytes = first[..first.len() - 1].to_vec();
    bytes.push(x);
    bytes.extend_from_slice(&second);
    fw.handle_bytes(&bytes, t(1));
    let got = lines(&mut fw);
    assert_eq!(got.len(), 1, "{got:?}");
    assert_eq!(got[0].0, Some(1));
    assert!(
        got[0].1.contains("N2 G1 X2"),
        "line 1 ran with line 2 inside: {got:?}"
    );
}

#[test]
fn rrf_drops_a_bad_line_silently_and_runs_the_next() {
    let mut fw = model(Dialect::Rrf, |c| c.rrf_marlin_mode = true);
    fw.handle_bytes(b"N1 G1 X1*0\n", t(1));
    send(&mut fw, 2, "G1 X2", t(1));
    assert_eq!(replies(&mut fw), vec!["ok"]);
    assert_eq!(lines(&mut fw), vec![(Some(2), "G1 X2".into())]);
    assert_eq!(fw.stats().lines_dropped, 1);
    // The dropped line still set the line number: the last line parsed.
    fw.handle_bytes(b"N7 G1 X1*0\n", t(2));
    assert_eq!(fw.last_line_number(), 7);
}

#[test]
fn rrf_hole_a_corrupted_star_runs_the_line_unchecked() {
    let mut fw = model(Dialect::Rrf, |c| c.rrf_marlin_mode = true);
    let mut bytes = numbered_line(1, "G1 X1");
    let star = bytes.iter().position(|&b| b == b'*').unwrap();
    bytes[star] = b'#';
    fw.handle_bytes(&bytes, t(1));
    assert_eq!(replies(&mut fw), vec!["ok"]);
    let got = lines(&mut fw);
    assert_eq!(got.len(), 1);
    assert!(got[0].1.starts_with("G1 X1#"), "{got:?}");
}

#[test]
fn rrf_answers_in_its_own_mode_until_m555_p2_and_reports_line_numbers() {
    let mut fw = model(Dialect::Rrf, |_| {});
    fw.handle_bytes(b"M555 P2\n", t(1));
    assert_eq!(replies(&mut fw), vec!["ok"]);
    let mut fw = model(Dialect::Rrf, |_| {});
    fw.handle_bytes(b"G1 X1\n", t(1));
    assert_eq!(replies(&mut fw), vec![""]);
    send(&mut fw, 41, "G1 X2", t(2));
    fw.handle_bytes(b"M409 K\"inputs\"\n", t(3));
    let r = replies(&mut fw);
    let v: serde_json::Value = serde_json::from_str(&r[1]).unwrap();
    let usb = v["result"]
        .as_array()
        .unwrap()
        .iter()
        .find(|i| i["name"] == "USB")
        .unwrap();
    assert_eq!(usb["lineNumber"], 42, "the query's own line counts one");
}

#[test]
fn rrf_urgent_m112_only_at_a_line_start_without_a_number() {
    let mut fw = model(Dialect::Rrf, |c| c.planner_blocks = 0);
    send(&mut fw, 1, "G1 X1", t(1)); // blocks the one command slot
    send(&mut fw, 2, "M112", t(2));
    assert!(!fw.is_halted());
    fw.handle_bytes(b"\nM112\n", t(3));
    assert!(fw.is_halted());
}

#[test]
fn klipper_ignores_numbers_and_checksums_and_acks_every_line() {
    let mut fw = model(Dialect::Klipper, |_| {});
    fw.handle_bytes(b"N5 G1 X1*0\nG1 X2\nM115\n", t(1));
    let r = replies(&mut fw);
    assert_eq!(&r[..2], ["ok", "ok"]);
    assert!(r[2].starts_with("ok FIRMWARE_NAME:Klipper"));
    assert_eq!(
        lines(&mut fw).into_iter().map(|l| l.1).collect::<Vec<_>>(),
        vec!["G1 X1", "G1 X2", "M115"]
    );
}

#[test]
fn klipper_m112_is_out_of_band_below_20_pending_lines() {
    let mut fw = model(Dialect::Klipper, |c| c.planner_blocks = 0);
    fw.handle_bytes(b"G1 X1\nG1 X2\nN3 M112\n", t(1));
    assert!(fw.is_halted());
    assert_eq!(replies(&mut fw), vec!["// Klipper state: Shutdown"]);
    fw.handle_bytes(b"G1 X3\n", t(2));
    assert_eq!(
        replies(&mut fw),
        vec!["!! Shutdown due to M112 command", "ok"]
    );
    fw.reset(t(3));
    assert_eq!(replies(&mut fw), vec!["// Klipper state: Disconnect"]);
    fw.handle_bytes(b"G1 X4\n", t(4));
    assert_eq!(replies(&mut fw), vec!["!! Printer is not ready", "ok"]);
    assert!(lines(&mut fw).is_empty(), "nothing runs while restarting");
    assert_eq!(fw.next_timeout(), Some(t(2003)));
    fw.handle_timeout(t(2003));
    assert_eq!(replies(&mut fw), vec!["// Klipper state: Ready"]);
    // With 20 lines pending (moves blocked), M112 waits its turn.
    let mut fw = model(Dialect::Klipper, |c| c.planner_blocks = 0);
    let mut bytes = Vec::new();
    for i in 0..25 {
        bytes.extend_from_slice(format!("G1 X{i}\n").as_bytes());
    }
    bytes.extend_from_slice(b"M112\n");
    fw.handle_bytes(&bytes, t(1));
    assert!(!fw.is_halted());
}

/// `manual_stepper.py`: a registered axis refuses `SET_POSITION` and a second
/// `GCODE_AXIS=<letter>`, word for word, with `!!` then `ok`, and the line does nothing;
/// `GCODE_AXIS=` releases it (a no-op when not registered); a restart forgets it.
#[test]
fn klipper_manual_stepper_axes_refuse_as_klipper_does() {
    let mut fw = model(Dialect::Klipper, |_| {});
    let s = "MANUAL_STEPPER STEPPER=syringe_a";
    let run = |fw: &mut Firmware, line: &str| {
        fw.handle_bytes(format!("{line}\n").as_bytes(), t(1));
        let r = replies(fw);
        lines(fw);
        r
    };
    assert_eq!(run(&mut fw, &format!("{s} GCODE_AXIS=")), ["ok"]);
    assert_eq!(run(&mut fw, &format!("{s} SET_POSITION=0")), ["ok"]);
    assert_eq!(run(&mut fw, &format!("{s} GCODE_AXIS=A")), ["ok"]);
    assert_eq!(
        run(&mut fw, &format!("{s} SET_POSITION=0")),
        ["!! Must unregister from gcode axis first", "ok"]
    );
    assert_eq!(
        run(&mut fw, &format!("{s} GCODE_AXIS=A")),
        ["!! Must unregister axis first", "ok"]
    );
    assert_eq!(
        run(&mut fw, "MANUAL_STEPPER STEPPER=syringe_b GCODE_AXIS=A"),
        ["!! Axis 'A' already registered", "ok"]
    );
    assert_eq!(
        run(&mut fw, "MANUAL_STEPPER STEPPER=syringe_b GCODE_AXIS=E"),
        ["!! Not a valid GCODE_AXIS", "ok"]
    );
    fw.handle_bytes(format!("{s} MOVE=1\n").as_bytes(), t(1));
    assert_eq!(
        replies(&mut fw),
        ["!! Must unregister from gcode axis first", "ok"]
    );
    assert!(lines(&mut fw).is_empty(), "a refused line does nothing");
    assert_eq!(run(&mut fw, &format!("{s} GCODE_AXIS=")), ["ok"]);
    assert_eq!(run(&mut fw, &format!("{s} MOVE=1")), ["ok"]);
    assert_eq!(run(&mut fw, &format!("{s} GCODE_AXIS=A")), ["ok"]);
    fw.reset(t(2));
    replies(&mut fw);
    fw.handle_bytes(format!("{s} SET_POSITION=0\n").as_bytes(), t(10_000));
    assert_eq!(
        replies(&mut fw),
        ["// Klipper state: Ready", "ok"],
        "a restart forgets the registration"
    );
}
