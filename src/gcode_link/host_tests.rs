//! Unit tests of the host end against scripted firmware replies.

use super::*;
use crate::gcode_link::{checksum, numbered_line};

const MARLIN_ID: &str = "FIRMWARE_NAME:Marlin 2.1.2.5 (test) PROTOCOL_VERSION:1.0";

fn t(ms: u64) -> Micros {
    Micros(ms * 1000)
}

fn cfg(dialect: Dialect) -> LineLinkConfig {
    LineLinkConfig::for_dialect(dialect)
}

/// Everything the host wants to write at `now`, as text.
fn tx(h: &mut LineHost, now: Micros) -> Vec<String> {
    let mut out = Vec::new();
    while let Some(b) = h.poll_transmit(now) {
        out.push(String::from_utf8_lossy(&b).into_owned());
    }
    out
}

fn events(h: &mut LineHost) -> Vec<LineEvent> {
    std::iter::from_fn(|| h.poll_event()).collect()
}

fn feed(h: &mut LineHost, text: &str, now: Micros) {
    h.handle_bytes(text.as_bytes(), now);
}

fn accepted(ev: &[LineEvent]) -> Vec<u64> {
    ev.iter()
        .filter_map(|e| match e {
            LineEvent::Accepted { tag, .. } => Some(*tag),
            _ => None,
        })
        .collect()
}

fn line(n: u32, text: &str) -> String {
    String::from_utf8_lossy(&numbered_line(n, text)).into_owned()
}

/// A host through the handshake with `first_ok` as the answer to `M110`.
fn connected_with(mut c: LineLinkConfig, first_ok: &str) -> LineHost {
    let dialect = c.dialect;
    c.history_lines = c.history_lines.max(8);
    let mut h = LineHost::new(c);
    h.connect(t(0));
    match dialect {
        Dialect::Marlin => {
            assert_eq!(tx(&mut h, t(0)), vec!["N0 M110 N0*125\n"]);
            feed(&mut h, first_ok, t(1));
            assert_eq!(tx(&mut h, t(1)), vec!["N1 M115*39\n"]);
            feed(
                &mut h,
                &format!("{MARLIN_ID}\nCap:EMERGENCY_PARSER:1\n{first_ok}"),
                t(2),
            );
        }
        Dialect::Rrf => {
            assert_eq!(tx(&mut h, t(0)), vec!["M555 P2\n"]);
            feed(&mut h, "\n", t(1));
            assert_eq!(tx(&mut h, t(1)), vec!["N0 M110 N0*125\n"]);
            feed(&mut h, "ok\n", t(1));
            assert_eq!(tx(&mut h, t(1)), vec!["N1 M115*39\n"]);
            feed(
                &mut h,
                "FIRMWARE_NAME: RepRapFirmware for Duet 3 MB6HC FIRMWARE_VERSION: 3.5.1\nok\n",
                t(2),
            );
        }
        Dialect::Klipper => {
            assert_eq!(tx(&mut h, t(0)), vec!["M115\n"]);
            feed(
                &mut h,
                "ok FIRMWARE_NAME:Klipper FIRMWARE_VERSION:v0.12.0\n",
                t(2),
            );
        }
    }
    assert_eq!(h.state(), LinkState::Streaming);
    let ev = events(&mut h);
    assert!(matches!(ev.last(), Some(LineEvent::Connected(_))), "{ev:?}");
    h
}

fn connected(dialect: Dialect) -> LineHost {
    connected_with(cfg(dialect), "ok\n")
}

fn windowed(lines: u16) -> LineHost {
    let mut c = cfg(Dialect::Marlin);
    c.window = Window::Lines(lines);
    c.rx_buffer_bytes = 4096;
    connected_with(c, "ok\n")
}

fn send(h: &mut LineHost, tags: std::ops::Range<u64>) {
    for tag in tags {
        h.send_line(&format!("G1 X{tag}"), tag).unwrap();
    }
}

#[test]
fn marlin_handshake_reports_the_firmware_and_numbers_lines_from_2() {
    let mut h = LineHost::new(cfg(Dialect::Marlin));
    h.connect(t(0));
    assert_eq!(tx(&mut h, t(0)), vec!["N0 M110 N0*125\n"]);
    feed(&mut h, "ok\n", t(1));
    assert_eq!(tx(&mut h, t(1)), vec!["N1 M115*39\n"]);
    feed(
        &mut h,
        &format!("{MARLIN_ID}\nCap:EMERGENCY_PARSER:1\nCap:BUSY_PROTOCOL:1\nok\n"),
        t(2),
    );
    let ev = events(&mut h);
    let Some(LineEvent::Connected(info)) = ev.last() else {
        panic!("{ev:?}")
    };
    assert_eq!(info.firmware_name.as_deref(), Some("Marlin 2.1.2.5 (test)"));
    assert_eq!(info.capability("EMERGENCY_PARSER"), Some(true));
    assert_eq!(info.capability("BUSY_PROTOCOL"), Some(true));
    h.send_line("G1 X1 Y2", 7).unwrap();
    let sent = tx(&mut h, t(3));
    assert_eq!(sent, vec![line(2, "G1 X1 Y2")]);
    let cs = checksum(b"N2 G1 X1 Y2");
    assert_eq!(sent[0], format!("N2 G1 X1 Y2*{cs}\n"));
}

#[test]
fn rrf_handshake_takes_an_empty_line_for_m555_and_sends_numbered_lines() {
    let mut h = connected(Dialect::Rrf);
    assert_eq!(h.firmware_info().firmware_version.as_deref(), Some("3.5.1"));
    h.send_line("G1 X1", 1).unwrap();
    assert_eq!(tx(&mut h, t(3)), vec![line(2, "G1 X1")]);
}

#[test]
fn klipper_handshake_reads_m115_from_the_ok_line_and_lines_go_plain() {
    let mut h = connected(Dialect::Klipper);
    assert_eq!(h.firmware_info().firmware_name.as_deref(), Some("Klipper"));
    send(&mut h, 0..3);
    assert_eq!(tx(&mut h, t(3)), vec!["G1 X0\n", "G1 X1\n", "G1 X2\n"]);
    feed(&mut h, "ok\nok\n", t(4));
    assert_eq!(accepted(&events(&mut h)), vec![0, 1]);
}

#[test]
fn a_stale_ok_does_not_complete_the_m115_step() {
    let mut h = LineHost::new(cfg(Dialect::Marlin));
    h.connect(t(0));
    tx(&mut h, t(0));
    feed(&mut h, "start\n", t(1)); // the board booted: the handshake starts again
    assert_eq!(tx(&mut h, t(1)), vec!["N0 M110 N0*125\n"]);
    feed(&mut h, "ok\nok\n", t(2)); // both M110s answered
    assert_eq!(tx(&mut h, t(2)), vec!["N1 M115*39\n"]);
    assert_eq!(h.state(), LinkState::Connecting);
    feed(&mut h, &format!("{MARLIN_ID}\nok\n"), t(3));
    assert_eq!(h.state(), LinkState::Streaming);
}

#[test]
fn handshake_gives_up_after_its_attempts() {
    let mut h = LineHost::new(cfg(Dialect::Marlin));
    h.connect(t(0));
    let mut sent = 0;
    let mut now = t(0);
    while h.state() == LinkState::Connecting {
        sent += tx(&mut h, now).len();
        now = h.next_timeout().unwrap();
        h.handle_timeout(now);
    }
    assert_eq!(h.state(), LinkState::Lost);
    assert_eq!(sent, 5);
    assert!(matches!(events(&mut h)[..], [LineEvent::LinkLost { .. }]));
}

#[test]
fn lines_that_would_break_the_checksum_or_numbering_are_refused() {
    let mut h = connected(Dialect::Marlin);
    for bad in [
        "",
        "G1 X1 ; go",
        "G1 X1*12",
        " G1",
        "N5 G1",
        "M110 N9",
        "M112",
        "G1 X\u{e9}",
        "G1\tX1",
        "M117 (hi)",
        "M117 a\\b",
    ] {
        assert!(
            matches!(h.send_line(bad, 0), Err(SendError::Invalid(_))),
            "{bad:?}"
        );
    }
    let long = format!("M117 {}", "x".repeat(90));
    assert!(matches!(
        h.send_line(&long, 0),
        Err(SendError::TooLong { max: 95, .. })
    ));
    assert_eq!(h.queued_len(), 0);
    let mut idle = LineHost::new(cfg(Dialect::Marlin));
    assert_eq!(
        idle.send_line("G1", 0),
        Err(SendError::NotReady(LinkState::Idle))
    );
}

#[test]
fn oks_acknowledge_lines_in_order_with_their_tags() {
    let mut h = connected(Dialect::Marlin);
    send(&mut h, 10..13);
    for (i, tag) in (10..13).enumerate() {
        assert_eq!(tx(&mut h, t(3 + i as u64)).len(), 1, "window 1");
        assert!(tx(&mut h, t(3 + i as u64)).is_empty());
        feed(&mut h, "ok\n", t(3 + i as u64));
        assert_eq!(
            events(&mut h),
            vec![LineEvent::Accepted {
                tag,
                line_number: 2 + i as u32
            }]
        );
    }
}

#[test]
fn resend_goes_back_and_ignores_the_repeats_of_lines_sent_before() {
    let mut h = windowed(4);
    send(&mut h, 0..6);
    let first = tx(&mut h, t(3));
    assert_eq!(
        first,
        vec![
            line(2, "G1 X0"),
            line(3, "G1 X1"),
            line(4, "G1 X2"),
            line(5, "G1 X3")
        ]
    );
    // Line 3 arrived corrupted: 2 accepted; 4 and 5 are drained or refused.
    feed(
        &mut h,
        "ok\nError:checksum mismatch, Last Line: 2\nResend: 3\nok\n",
        t(4),
    );
    assert_eq!(accepted(&events(&mut h)), vec![0]);
    assert_eq!(
        tx(&mut h, t(4)),
        vec![
            line(3, "G1 X1"),
            line(4, "G1 X2"),
            line(5, "G1 X3"),
            line(6, "G1 X4")
        ]
    );
    // Line 4 (old copy) was refused: a repeat of the same request, ignored with its ok.
    feed(
        &mut h,
        "Error:Line Number is not Last Line Number+1, Last Line: 2\nResend: 3\nok\n",
        t(5),
    );
    assert!(tx(&mut h, t(5)).is_empty());
    feed(&mut h, "ok\nok\nok\nok\n", t(6));
    assert_eq!(accepted(&events(&mut h)), vec![1, 2, 3, 4]);
    assert_eq!(h.stats().resends_duplicate, 1);
    assert_eq!(h.stats().oks_swallowed, 2);
    assert_eq!(tx(&mut h, t(6)), vec![line(7, "G1 X5")]);
}

#[test]
fn a_resend_for_a_line_the_firmware_already_confirmed_is_ignored() {
    let mut h = windowed(4);
    send(&mut h, 0..3);
    tx(&mut h, t(3));
    feed(
        &mut h,
        "ok\nok\nError:checksum mismatch, Last Line: 3\nResend: 4\nok\n",
        t(4),
    );
    assert_eq!(tx(&mut h, t(4)), vec![line(4, "G1 X2")]);
    feed(&mut h, "Resend: 3\nok\n", t(5)); // a delayed or corrupted request: 3 is confirmed
    assert!(tx(&mut h, t(5)).is_empty());
    assert_eq!(h.stats().resends_stale, 1);
    assert_eq!(h.state(), LinkState::Streaming);
}

#[test]
fn a_resend_for_a_line_never_sent_stops_the_job() {
    let mut h = windowed(4);
    send(&mut h, 0..4);
    tx(&mut h, t(3));
    feed(&mut h, "ok\nResend: 40\nok\n", t(4));
    let ev = events(&mut h);
    let Some(LineEvent::Stopped {
        reason,
        unacknowledged,
    }) = ev.last()
    else {
        panic!("{ev:?}")
    };
    assert!(reason.contains("never sent"), "{reason}");
    assert_eq!(unacknowledged, &vec![1, 2, 3]);
    assert_eq!(h.state(), LinkState::Stopped);
    assert!(tx(&mut h, t(5)).is_empty());
}

#[test]
fn a_resend_for_a_line_no_longer_kept_stops_the_job() {
    let mut c = cfg(Dialect::Marlin);
    c.window = Window::Lines(2);
    c.history_lines = 3;
    let mut h = connected_with(c, "ok\n");
    send(&mut h, 0..10);
    for i in 0..10 {
        tx(&mut h, t(3 + i));
        feed(&mut h, "ok\n", t(3 + i));
    }
    // Plain oks confirm nothing: the firmware may still ask for line 3, which is gone.
    feed(&mut h, "Resend: 3\nok\n", t(20));
    let ev = events(&mut h);
    assert!(
        matches!(ev.last(), Some(LineEvent::Stopped { reason, .. }) if reason.contains("no longer kept")),
        "{ev:?}"
    );
}

#[test]
fn error_and_resend_that_disagree_are_both_ignored() {
    let mut h = windowed(2);
    send(&mut h, 0..2);
    tx(&mut h, t(3));
    feed(
        &mut h,
        "Error:checksum mismatch, Last Line: 2\nResend: 7\nok\n",
        t(4),
    );
    let ev = events(&mut h);
    assert!(ev
        .iter()
        .any(|e| matches!(e, LineEvent::ProtocolError { what } if what.contains("both ignored"))));
    assert!(tx(&mut h, t(4)).is_empty());
    assert_eq!(h.stats().oks_swallowed, 1);
    assert_eq!(h.in_flight_len(), 2);
}

#[test]
fn an_error_whose_resend_line_was_lost_still_goes_back() {
    let mut h = windowed(2);
    send(&mut h, 0..2);
    tx(&mut h, t(3));
    feed(&mut h, "Error:checksum mismatch, Last Line: 1\nok\n", t(4));
    assert_eq!(tx(&mut h, t(4)), vec![line(2, "G1 X0"), line(3, "G1 X1")]);
    assert_eq!(h.stats().oks_swallowed, 1);
}

#[test]
fn an_ok_with_no_line_in_flight_is_reported_and_ignored() {
    let mut h = connected(Dialect::Marlin);
    feed(&mut h, "ok\n", t(3));
    let ev = events(&mut h);
    assert!(
        matches!(&ev[..], [LineEvent::ProtocolError { what }] if what.contains("no line in flight"))
    );
    assert_eq!(h.stats().oks_unexpected, 1);
}

#[test]
fn garbage_bytes_are_reported_and_the_link_goes_on() {
    let mut h = connected(Dialect::Marlin);
    send(&mut h, 0..1);
    tx(&mut h, t(3));
    h.handle_bytes(b"\xff\xfe\x80garbage\n\x00\x01\nok\n", t(4));
    let ev = events(&mut h);
    assert!(matches!(&ev[0], LineEvent::ProtocolError { what } if what.contains("not UTF-8")));
    assert!(matches!(&ev[1], LineEvent::Echo { .. }), "{ev:?}");
    assert_eq!(accepted(&ev), vec![0]);
    assert_eq!(h.stats().garbage_lines, 1);
}

#[test]
fn an_unterminated_megabyte_line_is_bounded_and_dropped_with_one_event() {
    let mut h = connected(Dialect::Marlin);
    send(&mut h, 0..1);
    tx(&mut h, t(3));
    let big = vec![b'A'; 1 << 20];
    for chunk in big.chunks(4096) {
        h.handle_bytes(chunk, t(4));
    }
    h.handle_bytes(b"\nok\n", t(5));
    let ev = events(&mut h);
    assert_eq!(
        ev.iter()
            .filter(
                |e| matches!(e, LineEvent::ProtocolError { what } if what.contains("longer than"))
            )
            .count(),
        1
    );
    assert_eq!(accepted(&ev), vec![0]);
    assert_eq!(h.stats().overlong_lines, 1);
}

#[test]
fn unknown_messages_actions_and_busy_are_reported() {
    let mut h = connected(Dialect::Marlin);
    feed(
        &mut h,
        "something odd\necho:Unknown command: \"G999\"\n//action:pause\necho:busy: processing\necho:busy: processing\n",
        t(3),
    );
    assert_eq!(
        events(&mut h),
        vec![
            LineEvent::Echo {
                text: "something odd".into()
            },
            LineEvent::Echo {
                text: "Unknown command: \"G999\"".into()
            },
            LineEvent::Action {
                text: "pause".into()
            },
            LineEvent::Busy {
                text: "processing".into()
            },
        ]
    );
}

#[test]
fn busy_keepalives_hold_off_the_timeout_and_silence_then_times_out_sooner() {
    let mut h = connected(Dialect::Marlin);
    send(&mut h, 0..1);
    tx(&mut h, t(3));
    assert_eq!(h.next_timeout(), Some(t(3).plus_us(10_000_000)));
    for s in 1..=10u64 {
        feed(&mut h, "echo:busy: processing\n", t(3 + 2000 * s));
        h.handle_timeout(t(3 + 2000 * s));
        assert_eq!(h.state(), LinkState::Streaming);
    }
    // Keepalives are known now: 5 s of silence is a loss.
    assert_eq!(h.next_timeout(), Some(t(20_003).plus_us(5_000_000)));
}

#[test]
fn marlin_timeout_probes_and_resumes_after_the_last_line_accepted() {
    let mut h = windowed(3);
    send(&mut h, 0..3);
    tx(&mut h, t(3));
    feed(&mut h, "ok\n", t(4)); // line 2; the oks of 3 and 4 are lost
    events(&mut h);
    let deadline = h.next_timeout().unwrap();
    let sent = tx(&mut h, deadline);
    assert_eq!(sent, vec![format!("\n{}", line(PROBE_LINE_NUMBER, "M105"))]);
    assert_eq!(h.state(), LinkState::Probing);
    assert!(
        h.send_line("G1 X9", 9).is_ok(),
        "lines may be queued while probing"
    );
    feed(
        &mut h,
        "Error:Line Number is not Last Line Number+1, Last Line: 3\nResend: 4\nok\n",
        deadline,
    );
    assert_eq!(accepted(&events(&mut h)), vec![1]);
    assert_eq!(h.state(), LinkState::Streaming);
    // Line 3 is not sent again; line 4 is.
    assert_eq!(
        tx(&mut h, deadline),
        vec![line(4, "G1 X2"), line(5, "G1 X9")]
    );
}

#[test]
fn a_probe_answer_that_goes_back_is_a_reset() {
    let mut h = windowed(2);
    send(&mut h, 0..2);
    tx(&mut h, t(3));
    feed(&mut h, "ok N2 P15 B3\nok N3 P15 B3\n", t(4));
    send(&mut h, 2..3);
    tx(&mut h, t(4));
    let deadline = h.next_timeout().unwrap();
    tx(&mut h, deadline);
    // A lone line going back is not trusted...
    feed(&mut h, "Resend: 1\nok\n", deadline);
    assert_eq!(h.state(), LinkState::Probing);
    // ...the pair is: the firmware restarted.
    feed(
        &mut h,
        "Error:Line Number is not Last Line Number+1, Last Line: 0\nResend: 1\nok\n",
        deadline,
    );
    let ev = events(&mut h);
    assert!(
        matches!(ev.last(), Some(LineEvent::Reset { unacknowledged, .. }) if unacknowledged == &vec![2]),
        "{ev:?}"
    );
}

#[test]
fn unanswered_probes_end_in_link_lost() {
    let mut h = connected(Dialect::Marlin);
    send(&mut h, 0..2);
    tx(&mut h, t(3));
    let mut probes = 0;
    while h.state() != LinkState::Lost {
        let now = h.next_timeout().unwrap();
        probes += tx(&mut h, now).len();
    }
    assert_eq!(probes, 3);
    let ev = events(&mut h);
    assert!(
        matches!(&ev[..], [LineEvent::LinkLost { unacknowledged, silent_us }] if unacknowledged == &vec![0, 1] && *silent_us > 10_000_000),
        "{ev:?}"
    );
}

#[test]
fn wait_with_old_lines_in_flight_probes_at_once() {
    let mut h = connected(Dialect::Marlin);
    send(&mut h, 0..1);
    tx(&mut h, t(3));
    feed(&mut h, "wait\n", t(500));
    assert!(
        tx(&mut h, t(500)).is_empty(),
        "too soon: the line may still be arriving"
    );
    feed(&mut h, "wait\n", t(1500));
    assert_eq!(h.state(), LinkState::Probing);
}

fn rrf_query(n: u32) -> String {
    format!("\n{}", line(n, "M409 K\"move.axes\" F\"f\""))
}

fn rrf_at(x_mm: f64) -> String {
    format!(
        "{{\"key\":\"move.axes\",\"flags\":\"f\",\"result\":[{{\"machinePosition\":{x_mm},\"userPosition\":{x_mm}}},{{\"userPosition\":0}},{{\"userPosition\":0}}]}}\n"
    )
}

/// RRF with line 2 (`G1 X0`) acknowledged and line 3 (`G1 X1`) in flight past its
/// timeout: the host asks where the nozzle stands.
fn rrf_line_3_overdue() -> (LineHost, Micros) {
    let mut h = connected(Dialect::Rrf);
    send(&mut h, 0..3);
    assert_eq!(tx(&mut h, t(3)), vec![line(2, "G1 X0")]);
    feed(&mut h, "ok\n", t(4));
    assert_eq!(tx(&mut h, t(4)), vec![line(3, "G1 X1")]);
    assert_eq!(accepted(&events(&mut h)), vec![0]);
    let deadline = h.next_timeout().unwrap();
    assert_eq!(deadline, t(4).plus_us(4_000_000));
    assert_eq!(tx(&mut h, deadline), vec![rrf_query(3)]);
    assert_eq!(h.state(), LinkState::Probing);
    (h, deadline)
}

#[test]
fn rrf_lost_ok_is_known_by_the_nozzles_position_and_nothing_runs_twice() {
    let (mut h, at) = rrf_line_3_overdue();
    feed(&mut h, &format!("{}ok\n", rrf_at(1.0)), at);
    let ev = events(&mut h);
    assert_eq!(accepted(&ev), vec![1]);
    assert!(!ev
        .iter()
        .any(|e| matches!(e, LineEvent::MaybeRepeated { .. })));
    assert_eq!(tx(&mut h, at), vec![line(4, "G1 X2")]);
    feed(&mut h, "ok\n", at);
    assert_eq!(accepted(&events(&mut h)), vec![2]);
    assert_eq!(h.stats().ran_by_position, 1);
    assert_eq!(h.stats().lines_repeated, 0);
}

#[test]
fn rrf_dropped_line_is_known_by_position_and_sent_again_not_repeated() {
    let (mut h, at) = rrf_line_3_overdue();
    feed(&mut h, &format!("{}ok\n", rrf_at(0.0)), at);
    assert!(events(&mut h).is_empty());
    assert_eq!(tx(&mut h, at), vec![line(3, "G1 X1")]);
    feed(&mut h, "ok\n", at);
    assert_eq!(accepted(&events(&mut h)), vec![1]);
    assert_eq!(h.stats().dropped_by_position, 1);
    assert_eq!(h.stats().lines_repeated, 0);
}

#[test]
fn rrf_late_ok_before_the_position_counts_once_for_its_line() {
    let (mut h, at) = rrf_line_3_overdue();
    feed(&mut h, &format!("ok\n{}ok\n", rrf_at(1.0)), at);
    assert_eq!(accepted(&events(&mut h)), vec![1]);
    assert_eq!(tx(&mut h, at), vec![line(4, "G1 X2")]);
    feed(&mut h, "ok\n", at);
    assert_eq!(accepted(&events(&mut h)), vec![2]);
    assert_eq!(h.stats().oks_unexpected, 0);
}

#[test]
fn rrf_query_answered_late_owes_one_ok_per_query() {
    let (mut h, at) = rrf_line_3_overdue();
    let again = h.next_timeout().unwrap();
    assert_eq!(
        again,
        at.plus_us(4_000_000),
        "asked again after the ok timeout"
    );
    assert_eq!(
        tx(&mut h, again),
        vec![rrf_query(3)],
        "no answer: asked again"
    );
    // Both answers, in order; the first decides, the rest are swallowed.
    feed(&mut h, &format!("{}ok\n", rrf_at(1.0)), again);
    assert_eq!(accepted(&events(&mut h)), vec![1]);
    feed(&mut h, &format!("{}ok\n", rrf_at(1.0)), again);
    assert_eq!(tx(&mut h, again), vec![line(4, "G1 X2")]);
    feed(&mut h, "ok\n", again);
    assert_eq!(accepted(&events(&mut h)), vec![2]);
    assert_eq!(h.stats().oks_unexpected, 0);
}

#[test]
fn rrf_position_that_cannot_tell_sends_the_line_again_and_says_so() {
    let mut h = connected(Dialect::Rrf);
    h.send_line("G1 X5", 0).unwrap();
    h.send_line("G1 E-0.2", 1).unwrap();
    assert_eq!(tx(&mut h, t(3)), vec![line(2, "G1 X5")]);
    feed(&mut h, "ok\n", t(4));
    assert_eq!(tx(&mut h, t(4)).len(), 1);
    let deadline = h.next_timeout().unwrap();
    assert_eq!(tx(&mut h, deadline), vec![rrf_query(3)]);
    feed(&mut h, &format!("{}ok\n", rrf_at(5.0)), deadline);
    let ev = events(&mut h);
    assert!(ev.contains(&LineEvent::MaybeRepeated {
        tag: 1,
        line_number: 3
    }));
    assert_eq!(tx(&mut h, deadline), vec![line(3, "G1 E-0.2")]);
    // Nowhere near either end: said, and sent again.
    let (mut h, at) = rrf_line_3_overdue();
    feed(&mut h, &format!("{}ok\n", rrf_at(40.0)), at);
    let ev = events(&mut h);
    assert!(ev
        .iter()
        .any(|e| matches!(e, LineEvent::ProtocolError { what } if what.contains("neither"))));
    assert!(ev
        .iter()
        .any(|e| matches!(e, LineEvent::MaybeRepeated { .. })));
}

#[test]
fn klipper_timeout_never_resends_and_ends_in_link_lost() {
    let mut h = connected(Dialect::Klipper);
    send(&mut h, 0..1);
    tx(&mut h, t(3));
    let mut sent = 0;
    while h.state() == LinkState::Streaming {
        let now = h.next_timeout().unwrap();
        sent += tx(&mut h, now).len();
    }
    assert_eq!(sent, 0);
    assert_eq!(h.state(), LinkState::Lost);
}

#[test]
fn slow_commands_get_the_long_timeout() {
    let mut h = connected(Dialect::Marlin);
    h.send_line("G28", 0).unwrap();
    tx(&mut h, t(3));
    assert_eq!(h.next_timeout(), Some(t(3).plus_us(900_000_000)));
}

#[test]
fn marlin_start_banner_is_a_reset_and_nothing_more_is_sent() {
    let mut h = windowed(2);
    send(&mut h, 0..3);
    tx(&mut h, t(3));
    feed(&mut h, "ok\nstart\nPowerUp\n", t(4));
    let ev = events(&mut h);
    assert_eq!(accepted(&ev), vec![0]);
    assert!(
        matches!(ev.last(), Some(LineEvent::Reset { banner, unacknowledged }) if banner == "start" && unacknowledged == &vec![1, 2]),
        "{ev:?}"
    );
    assert!(tx(&mut h, t(5)).is_empty());
    assert_eq!(h.connect(t(6)), vec![1, 2]);
    assert_eq!(tx(&mut h, t(6)), vec!["N0 M110 N0*125\n"]);
}

#[test]
fn klipper_ready_is_a_reset_and_shutdown_a_halt() {
    let mut h = connected(Dialect::Klipper);
    feed(&mut h, "// Klipper state: Ready\n", t(3));
    assert!(matches!(events(&mut h)[..], [LineEvent::Reset { .. }]));
    let mut h = connected(Dialect::Klipper);
    send(&mut h, 0..1);
    tx(&mut h, t(3));
    feed(
        &mut h,
        "!! Shutdown due to M112 command\n// Klipper state: Shutdown\n",
        t(3),
    );
    let ev = events(&mut h);
    assert!(
        matches!(&ev[0], LineEvent::Halted { unacknowledged, .. } if unacknowledged == &vec![0]),
        "{ev:?}"
    );
    assert_eq!(h.state(), LinkState::Halted);
}

/// Klipper answers a refused line `!! why`, then its `ok`: the link stops at that line,
/// naming it and the reply, and sends nothing more (a job must not carry on past it).
#[test]
fn klipper_refusal_stops_the_link_at_the_refused_line() {
    let mut h = connected(Dialect::Klipper);
    send(&mut h, 0..3);
    tx(&mut h, t(3));
    feed(
        &mut h,
        "ok
",
        t(4),
    );
    feed(
        &mut h,
        "!! Must unregister from gcode axis first
ok
",
        t(4),
    );
    let ev = events(&mut h);
    assert_eq!(accepted(&ev), vec![0, 1], "{ev:?}");
    let stopped = ev.iter().find_map(|e| match e {
        LineEvent::Stopped {
            reason,
            unacknowledged,
        } => Some((reason.clone(), unacknowledged.clone())),
        _ => None,
    });
    let (reason, unacknowledged) = stopped.expect("stopped");
    assert!(reason.contains("`G1 X1`"), "{reason}");
    assert!(
        reason.ends_with("!! Must unregister from gcode axis first"),
        "{reason}"
    );
    assert_eq!(unacknowledged, vec![2]);
    assert_eq!(h.state(), LinkState::Stopped);
    assert!(tx(&mut h, t(5)).is_empty());
}

#[test]
fn marlin_kill_halts_and_other_errors_stop_at_their_line() {
    let mut h = connected(Dialect::Marlin);
    send(&mut h, 0..2);
    tx(&mut h, t(3));
    feed(&mut h, "Error:Printer halted. kill() called!\n", t(5));
    assert!(matches!(events(&mut h)[..], [LineEvent::Halted { .. }]));
    assert!(tx(&mut h, t(6)).is_empty());

    let mut h = connected(Dialect::Marlin);
    send(&mut h, 0..2);
    tx(&mut h, t(3));
    feed(&mut h, "Error:Unknown mixer setting\nok\n", t(4));
    let ev = events(&mut h);
    assert_eq!(
        ev[0],
        LineEvent::Error {
            text: "Unknown mixer setting".into()
        }
    );
    assert_eq!(accepted(&ev), vec![0]);
    assert!(
        matches!(&ev[2], LineEvent::Stopped { reason, unacknowledged }
            if reason.contains("line 2 `N2 G1 X0") && reason.ends_with("Error:Unknown mixer setting")
                && unacknowledged == &vec![1]),
        "{ev:?}"
    );
}

#[test]
fn emergency_stop_goes_ahead_of_everything_and_ends_the_stream() {
    let mut h = windowed(2);
    send(&mut h, 0..5);
    tx(&mut h, t(3));
    assert_eq!(h.emergency_stop(), vec![0, 1, 2, 3, 4]);
    assert_eq!(tx(&mut h, t(3)), vec!["\nM112\n"]);
    assert_eq!(h.state(), LinkState::Halted);
    feed(&mut h, "ok\n", t(4));
    assert!(tx(&mut h, t(4)).is_empty());
}

#[test]
fn advanced_ok_opens_the_window_within_the_receive_buffer() {
    let mut c = cfg(Dialect::Marlin);
    c.rx_buffer_bytes = 128;
    c.window = Window::AdvancedOk;
    let mut h = connected_with(c, "ok N0 P16 B3\n");
    assert!(h.firmware_info().advanced_ok);
    assert_eq!(h.firmware_info().command_slots, Some(4));
    assert_eq!(h.window_lines(), 4);
    for tag in 0..6 {
        h.send_line(&format!("G1 X{tag}.000 Y1.000 E0.00100 F1800"), tag)
            .unwrap();
    }
    // 38-byte lines: three fit in 128 − 8 bytes.
    assert_eq!(tx(&mut h, t(3)).len(), 3);
    feed(&mut h, "ok N2 P15 B2\n", t(4));
    assert_eq!(
        h.free_counts(),
        Some(FreeCounts {
            planner_blocks: 15,
            command_slots: 3
        })
    );
    assert_eq!(tx(&mut h, t(4)).len(), 1);
}

#[test]
fn advanced_ok_number_ahead_is_trusted_only_when_the_next_ok_follows() {
    let mut h = windowed(4);
    send(&mut h, 0..4);
    tx(&mut h, t(3));
    // The ok of line 2 was lost: `ok N3` then `ok N4` confirm both.
    feed(&mut h, "ok N3 P15 B2\n", t(4));
    assert_eq!(accepted(&events(&mut h)), vec![0]);
    feed(&mut h, "ok N4 P15 B2\n", t(4));
    assert_eq!(accepted(&events(&mut h)), vec![1, 2]);
    assert_eq!(h.in_flight_len(), 1);
    // A corrupted number (`N9` for `N5`) counts for the oldest line only.
    feed(&mut h, "ok N9 P15 B2\n", t(5));
    assert_eq!(accepted(&events(&mut h)), vec![3]);
    assert_eq!(h.in_flight_len(), 0);
}

#[test]
fn an_unnumbered_ok_under_advanced_ok_is_a_line_the_firmware_ran_unchecked() {
    let mut h = windowed(2);
    send(&mut h, 0..2);
    tx(&mut h, t(3));
    feed(&mut h, "ok P15 B3\n", t(4));
    let ev = events(&mut h);
    assert!(
        matches!(&ev[..], [LineEvent::ProtocolError { what }] if what.contains("without a line number"))
    );
    assert_eq!(h.in_flight_len(), 2);
    // A corrupted `N` token is not that: the ok counts for the oldest line.
    feed(&mut h, "ok M2 P15 B3\n", t(4));
    assert_eq!(accepted(&events(&mut h)), vec![0]);
}

#[test]
fn marlin_recovery_after_a_host_restart_uses_the_probe() {
    let mut h = LineHost::new(cfg(Dialect::Marlin));
    h.recover_last_accepted(t(0)).unwrap();
    assert_eq!(h.state(), LinkState::Recovering);
    assert_eq!(
        tx(&mut h, t(0)),
        vec![format!("\n{}", line(PROBE_LINE_NUMBER, "M105"))]
    );
    // Old lines still arriving get oks; a lone Resend is not trusted.
    feed(&mut h, "ok\nResend: 41\nok\n", t(1));
    assert_eq!(h.state(), LinkState::Recovering);
    feed(
        &mut h,
        "Error:Line Number is not Last Line Number+1, Last Line: 40\nResend: 41\nok\n",
        t(2),
    );
    assert_eq!(
        events(&mut h),
        vec![LineEvent::LastAccepted(LastAccepted::Known {
            line_number: 40,
            tag: None,
            resume_tag: None,
            exact: true,
            position_um: None
        })]
    );
    assert_eq!(h.state(), LinkState::Idle);
}

/// After a host restart on a loaded machine the probe went out twice (its answer came
/// after the probe's timeout), and the second answer arrives during the handshake. Its
/// `Resend:` names a line of the old numbering, not one of the handshake's: it does not
/// restart the handshake (an `M110 N0` sent again behind `M115` sets the firmware's
/// line number back under the stream: "went back from 1 to 0", a reset), and its `ok`
/// is not taken for the handshake's.
#[test]
fn a_late_probe_answer_during_the_handshake_does_not_restart_it() {
    let mut h = LineHost::new(cfg(Dialect::Marlin));
    h.recover_last_accepted(t(0)).unwrap();
    let probe = format!("\n{}", line(PROBE_LINE_NUMBER, "M105"));
    assert_eq!(tx(&mut h, t(0)), vec![probe.clone()]);
    let c = h.config();
    let late = c.ok_timeout_us.max(c.handshake_timeout_us) / 1000 + 1;
    h.handle_timeout(t(late));
    assert_eq!(tx(&mut h, t(late)), vec![probe]);
    let answer = "Error:Line Number is not Last Line Number+1, Last Line: 287\nResend: 288\nok\n";
    feed(&mut h, answer, t(late + 1));
    assert!(
        matches!(
            events(&mut h)[..],
            [LineEvent::LastAccepted(LastAccepted::Known {
                line_number: 287,
                ..
            })]
        ),
        "the first answer recovers"
    );
    h.connect(t(late + 2));
    assert_eq!(tx(&mut h, t(late + 2)), vec!["N0 M110 N0*125\n"]);
    feed(&mut h, answer, t(late + 3));
    assert!(tx(&mut h, t(late + 3)).is_empty(), "M110 is not sent again");
    feed(&mut h, "ok\n", t(late + 4));
    assert_eq!(tx(&mut h, t(late + 4)), vec!["N1 M115*39\n"]);
    feed(&mut h, &format!("{MARLIN_ID}\nok\n"), t(late + 5));
    assert_eq!(h.state(), LinkState::Streaming);
}

/// The probe's answer split across two reads, the caller connecting in between (a
/// loaded host): the `ok` that ends the answer comes during the handshake and is not
/// taken for `M110`'s. Taken, every later `ok` counted for the line after its own, and
/// the next probe found the firmware "gone back from 1 to 0": a false reset that
/// interrupted the resumed job (`marlin_sigkill_mid_job_...`, about 1 run in 16 under
/// load).
#[test]
fn the_ok_ending_a_recovery_answer_is_not_the_handshakes() {
    let mut h = LineHost::new(cfg(Dialect::Marlin));
    h.recover_last_accepted(t(0)).unwrap();
    tx(&mut h, t(0));
    feed(
        &mut h,
        "Error:Line Number is not Last Line Number+1, Last Line: 311\nResend: 312\n",
        t(1),
    );
    assert!(matches!(
        events(&mut h)[..],
        [LineEvent::LastAccepted(LastAccepted::Known {
            line_number: 311,
            ..
        })]
    ));
    h.connect(t(2));
    assert_eq!(tx(&mut h, t(2)), vec!["N0 M110 N0*125\n"]);
    feed(&mut h, "ok\n", t(3));
    assert!(tx(&mut h, t(3)).is_empty(), "the answer's ok is not M110's");
    feed(&mut h, "ok\n", t(4));
    assert_eq!(tx(&mut h, t(4)), vec!["N1 M115*39\n"]);
    // Read whole, the answer's `ok` is dropped before the handshake: none is owed.
    let mut h = LineHost::new(cfg(Dialect::Marlin));
    h.recover_last_accepted(t(0)).unwrap();
    tx(&mut h, t(0));
    feed(
        &mut h,
        "Error:Line Number is not Last Line Number+1, Last Line: 311\nResend: 312\nok\n",
        t(1),
    );
    events(&mut h);
    h.connect(t(2));
    tx(&mut h, t(2));
    feed(&mut h, "ok\n", t(3));
    assert_eq!(tx(&mut h, t(3)), vec!["N1 M115*39\n"]);
}

#[test]
fn marlin_recovery_after_link_loss_names_the_line_to_resume_from() {
    let mut h = windowed(3);
    send(&mut h, 0..5);
    tx(&mut h, t(3));
    while h.state() != LinkState::Lost {
        let now = h.next_timeout().unwrap();
        tx(&mut h, now);
    }
    events(&mut h);
    h.recover_last_accepted(t(100_000)).unwrap();
    tx(&mut h, t(100_000));
    feed(
        &mut h,
        "Error:Line Number is not Last Line Number+1, Last Line: 3\nResend: 4\nok\n",
        t(100_001),
    );
    assert_eq!(
        events(&mut h),
        vec![LineEvent::LastAccepted(LastAccepted::Known {
            line_number: 3,
            tag: Some(1),
            resume_tag: Some(2),
            exact: true,
            position_um: None
        })]
    );
    assert_eq!(h.state(), LinkState::Lost);
}

#[test]
fn rrf_recovery_reads_line_number_from_m409() {
    let mut h = LineHost::new(cfg(Dialect::Rrf));
    h.recover_last_accepted(t(0)).unwrap();
    assert_eq!(tx(&mut h, t(0)), vec!["\nM409 K\"inputs\"\n"]);
    feed(&mut h, "{\"key\":\"inputs\",\"flags\":\"\",\"result\":[{\"name\":\"HTTP\",\"lineNumber\":3},null,{\"name\":\"USB\",\"lineNumber\":57}]}\nok\n", t(1));
    assert!(events(&mut h).is_empty(), "the position is asked next");
    assert_eq!(tx(&mut h, t(1)), vec![rrf_query(57)]);
    feed(&mut h, &rrf_at(12.5), t(2));
    assert_eq!(
        events(&mut h),
        vec![LineEvent::LastAccepted(LastAccepted::Known {
            line_number: 56,
            tag: None,
            resume_tag: None,
            exact: false,
            position_um: Some([12_500, 0, 0])
        })]
    );
    let mut h = LineHost::new(cfg(Dialect::Rrf));
    h.recover_last_accepted(t(0)).unwrap();
    tx(&mut h, t(0));
    feed(
        &mut h,
        "{\"key\":\"inputs\",\"result\":[{\"name\":\"HTTP\"}]}\n",
        t(1),
    );
    assert!(
        matches!(&events(&mut h)[..], [LineEvent::ProtocolError { what }] if what.contains("no input named"))
    );
    while h.state() == LinkState::Recovering {
        let now = h.next_timeout().unwrap();
        tx(&mut h, now);
    }
    assert!(matches!(
        &events(&mut h)[..],
        [LineEvent::LastAccepted(LastAccepted::Unknown { .. })]
    ));
}

#[test]
fn klipper_recovery_asks_where_the_nozzle_stopped_and_streaming_refuses_it() {
    let mut h = LineHost::new(cfg(Dialect::Klipper));
    h.recover_last_accepted(t(0)).unwrap();
    assert_eq!(tx(&mut h, t(0)), vec!["\nM400\nGET_POSITION\n"]);
    feed(
        &mut h,
        "ok\n// mcu: stepper_x:0\n// toolhead: X:9 Y:9 Z:9 E:0\n\
         // gcode: X:1.000000 Y:2.500000 Z:0.300000 E:0.000000\n\
         // gcode base: X:0.000000 Y:0.000000 Z:0.100000 E:0.000000\n\
         // gcode homing: X:0 Y:0 Z:0\nok\n",
        t(1),
    );
    let answers: Vec<_> = events(&mut h)
        .into_iter()
        .filter(|e| matches!(e, LineEvent::LastAccepted(_)))
        .collect();
    assert_eq!(
        answers,
        vec![LineEvent::LastAccepted(LastAccepted::Position {
            xyz_um: [1_000, 2_500, 200]
        })]
    );
    h.connect(t(2));
    assert_eq!(
        tx(&mut h, t(2)),
        vec!["M115\n"],
        "GET_POSITION's ok was not owed"
    );
    // Not ready: it cannot say; no answer: asked once, then not known.
    let mut h = LineHost::new(cfg(Dialect::Klipper));
    h.recover_last_accepted(t(0)).unwrap();
    tx(&mut h, t(0));
    feed(&mut h, "!! Printer is not ready\nok\n", t(1));
    assert!(matches!(
        &events(&mut h)[..],
        [LineEvent::LastAccepted(LastAccepted::Unknown { reason })] if reason.contains("not ready")
    ));
    let mut h = LineHost::new(cfg(Dialect::Klipper));
    h.recover_last_accepted(t(0)).unwrap();
    tx(&mut h, t(0));
    let deadline = h.next_timeout().unwrap();
    let c = h.config();
    let patience = c.ok_timeout_us * u64::from(c.max_timeouts);
    assert_eq!(
        deadline,
        t(0).plus_us(patience),
        "M400 waits for what Klipper holds"
    );
    assert!(tx(&mut h, deadline).is_empty(), "not asked again");
    assert!(matches!(
        &events(&mut h)[..],
        [LineEvent::LastAccepted(LastAccepted::Unknown { .. })]
    ));
    let mut h = connected(Dialect::Marlin);
    assert_eq!(
        h.recover_last_accepted(t(3)),
        Err(RecoverError::Busy(LinkState::Streaming))
    );
}

#[test]
fn port_closed_is_a_reset() {
    let mut h = connected(Dialect::Rrf);
    send(&mut h, 0..2);
    tx(&mut h, t(3));
    h.port_closed();
    assert!(
        matches!(&events(&mut h)[..], [LineEvent::Reset { unacknowledged, .. }] if unacknowledged == &vec![0, 1])
    );
}

#[test]
fn pause_holds_new_lines_but_not_resends() {
    let mut h = windowed(2);
    send(&mut h, 0..4);
    tx(&mut h, t(3));
    h.set_paused(true);
    feed(
        &mut h,
        "Error:checksum mismatch, Last Line: 2\nResend: 3\nok\n",
        t(4),
    );
    assert_eq!(tx(&mut h, t(4)), vec![line(3, "G1 X1")]);
    feed(&mut h, "ok\nok\n", t(5));
    assert!(tx(&mut h, t(5)).is_empty());
    assert_eq!(h.drop_queued(), vec![2, 3]);
    h.set_paused(false);
    assert!(tx(&mut h, t(6)).is_empty());
}

#[test]
fn a_resend_loop_stops_the_job() {
    let mut h = windowed(1);
    send(&mut h, 0..1);
    let mut stopped = false;
    for i in 0..12 {
        tx(&mut h, t(3 + i));
        feed(
            &mut h,
            "Error:checksum mismatch, Last Line: 1\nResend: 2\nok\n",
            t(3 + i),
        );
        if h.state() == LinkState::Stopped {
            stopped = true;
            break;
        }
    }
    assert!(stopped);
    assert!(events(&mut h).iter().any(
        |e| matches!(e, LineEvent::Stopped { reason, .. } if reason.contains("times in a row"))
    ));
}

#[test]
fn a_line_reported_accepted_from_a_plain_ok_is_sent_again_if_the_firmware_asks() {
    let mut h = windowed(2);
    send(&mut h, 0..2);
    tx(&mut h, t(3));
    // The error's `Resend:` and `ok` were lost and their ok was read as line 2's.
    feed(&mut h, "ok\n", t(4));
    assert_eq!(accepted(&events(&mut h)), vec![0]);
    feed(
        &mut h,
        "Error:checksum mismatch, Last Line: 1\nResend: 2\nok\n",
        t(5),
    );
    let ev = events(&mut h);
    assert!(ev
        .iter()
        .any(|e| matches!(e, LineEvent::ProtocolError { what } if what.contains("miscounted"))));
    assert_eq!(tx(&mut h, t(5)), vec![line(2, "G1 X0"), line(3, "G1 X1")]);
}

// Bad input from the machine (issue 30, "Bad input from the machine"): whatever comes,
// no panic, memory bounded, every line accepted once and in order, and a line goes out
// again only after a resend request or a probe (counted in the stats), never silently.

/// The numbered lines the host wrote, as (number, text).
fn numbered(sent: &[String]) -> Vec<(u32, String)> {
    sent.iter()
        .flat_map(|s| s.lines())
        .filter_map(|l| {
            let rest = l.strip_prefix('N')?;
            let (n, text) = rest.split_once(' ')?;
            let text = text.rsplit_once('*').map_or(text, |(t, _)| t);
            Some((n.parse().ok()?, text.to_string()))
        })
        .filter(|(n, _)| *n != PROBE_LINE_NUMBER)
        .collect()
}

#[test]
fn a_megabyte_of_seeded_garbage_between_oks_loses_and_repeats_nothing() {
    let mut h = connected(Dialect::Marlin);
    let mut rng = crate::link::testkit::SimRng::new(30);
    let mut sent = Vec::new();
    let mut acc = Vec::new();
    let mut garbage_bytes = 0usize;
    for tag in 0..64u64 {
        send(&mut h, tag..tag + 1);
        sent.extend(tx(&mut h, t(3 + tag)));
        // 16 KiB of bytes that are not UTF-8, cut into lines and not.
        let junk: Vec<u8> = (0..16_384)
            .map(|_| match rng.next_u64() % 64 {
                0 => b'\n',
                1 => b'\r',
                _ => 0x80 | (rng.next_u64() as u8),
            })
            .collect();
        garbage_bytes += junk.len();
        h.handle_bytes(&junk, t(3 + tag));
        h.handle_bytes(b"\nok\n", t(3 + tag));
        acc.extend(accepted(&events(&mut h)));
        assert!(h.reader.buffered_len() <= h.cfg.max_reply_line_bytes);
    }
    assert!(garbage_bytes >= 1 << 20);
    assert_eq!(acc, (0..64).collect::<Vec<_>>());
    let lines = numbered(&sent);
    let numbers: Vec<u32> = lines.iter().map(|(n, _)| *n).collect();
    assert_eq!(numbers, (2..66).collect::<Vec<_>>(), "each line once");
    assert!(h.stats().garbage_lines > 1000, "{:?}", h.stats());
    assert_eq!(h.stats().lines_resent, 0);
}

#[test]
fn an_unterminated_megabyte_line_keeps_memory_bounded_and_the_timeout_still_runs() {
    let mut h = connected(Dialect::Marlin);
    send(&mut h, 0..1);
    tx(&mut h, t(3));
    for _ in 0..256 {
        h.handle_bytes(&[b'x'; 4096], t(4));
        assert!(h.reader.buffered_len() <= h.cfg.max_reply_line_bytes);
    }
    // Nothing ended the line: no `ok` came, so the ok timeout probes, once.
    let deadline = h.next_timeout().unwrap();
    assert_eq!(
        tx(&mut h, deadline),
        vec![format!("\n{}", line(PROBE_LINE_NUMBER, "M105"))]
    );
    // The probe's answer arrives after the end of the long line; it is read.
    feed(
        &mut h,
        "tail\nError:Line Number is not Last Line Number+1, Last Line: 2\nResend: 3\nok\n",
        deadline,
    );
    assert_eq!(accepted(&events(&mut h)), vec![0]);
    assert_eq!(h.stats().overlong_lines, 1);
    assert_eq!(h.state(), LinkState::Streaming);
}

#[test]
fn a_line_ended_by_carriage_returns_only_is_bounded_too() {
    let mut h = connected(Dialect::Marlin);
    let oks = h.stats().oks;
    for _ in 0..64 {
        h.handle_bytes(&b"ok\r".repeat(1000), t(3));
    }
    assert!(h.reader.buffered_len() <= h.cfg.max_reply_line_bytes);
    h.handle_bytes(b"\n", t(3));
    assert_eq!(h.stats().overlong_lines, 1);
    assert_eq!(h.stats().oks, oks, "no `ok` is read out of a line of them");
}

/// A resend request whose number cannot be a line (corrupted, overflowing) sends no
/// line: Marlin's requests are answered by the probe, which asks the firmware.
#[test]
fn resend_requests_with_impossible_numbers_never_send_a_line() {
    for bad in [
        "Resend: 99999999999999999999999\nok\n",
        "Resend:\nok\n",
        "Resend: -3\nok\n",
        "rs abc\nok\n",
        "Resend: 4294967295\nok\n",
        "Error:checksum mismatch, Last Line: 4294967295\nResend: 0\nok\n",
        "Error:Line Number is not Last Line Number+1, Last Line: 99999999999999\nok\n",
    ] {
        let mut h = windowed(2);
        send(&mut h, 0..2);
        tx(&mut h, t(3));
        feed(&mut h, bad, t(4));
        let sent = tx(&mut h, t(4));
        assert!(numbered(&sent).is_empty(), "{bad:?}: sent {sent:?}");
        // The `ok` after a request belongs to the request: no line is counted from it.
        let ev = events(&mut h);
        assert!(accepted(&ev).is_empty(), "{bad:?}: {ev:?}");
        assert!(
            ev.iter().any(|e| matches!(
                e,
                LineEvent::ProtocolError { .. }
                    | LineEvent::Stopped { .. }
                    | LineEvent::Echo { .. }
            )),
            "{bad:?} is reported: {ev:?}"
        );
    }
}

#[test]
fn a_resend_for_a_line_acknowledged_long_ago_is_ignored_and_nothing_goes_twice() {
    let mut h = connected_with(cfg(Dialect::Marlin), "ok\n");
    let mut sent = Vec::new();
    for tag in 0..200 {
        send(&mut h, tag..tag + 1);
        sent.extend(tx(&mut h, t(3 + tag)));
        // ADVANCED_OK numbers confirm each line for good.
        feed(&mut h, &format!("ok N{} P15 B3\n", tag + 2), t(3 + tag));
    }
    feed(&mut h, "Resend: 5\nok\nResend: 150\nok\n", t(300));
    sent.extend(tx(&mut h, t(300)));
    let numbers: Vec<u32> = numbered(&sent).iter().map(|(n, _)| *n).collect();
    assert_eq!(numbers, (2..202).collect::<Vec<_>>());
    assert_eq!(h.stats().resends_stale, 2);
    assert_eq!(h.state(), LinkState::Streaming);
}

#[test]
fn oks_with_no_line_in_flight_in_every_state_are_ignored() {
    let mut h = connected(Dialect::Marlin);
    feed(&mut h, &"ok\n".repeat(100), t(3));
    assert_eq!(h.stats().oks_unexpected, 100);
    // They are not banked: the next line still waits for its own `ok`.
    send(&mut h, 0..2);
    tx(&mut h, t(4));
    assert!(accepted(&events(&mut h)).is_empty());
    assert_eq!(h.in_flight_len(), 1);
    feed(&mut h, "ok\n", t(5));
    assert_eq!(accepted(&events(&mut h)), vec![0]);
    // Once stopped, replies change nothing and send nothing.
    h.emergency_stop();
    tx(&mut h, t(6));
    feed(&mut h, "ok\nok\nResend: 3\nok\n", t(7));
    assert!(tx(&mut h, t(7)).is_empty());
    assert!(accepted(&events(&mut h)).is_empty());
}

#[test]
fn advanced_ok_numbers_and_counts_out_of_range_do_not_open_the_window() {
    let mut c = cfg(Dialect::Marlin);
    c.window = Window::AdvancedOk;
    let mut h = connected_with(c, "ok N0 P15 B3\n");
    send(&mut h, 0..40);
    tx(&mut h, t(3));
    feed(
        &mut h,
        "ok N99999999999 P99999999999 B99999999999\nok N-1 P-5 B-5\nok Nx Py Bz\n",
        t(4),
    );
    events(&mut h);
    tx(&mut h, t(4));
    // At most the slots the last good counts gave (B3: 4) and the buffer's bytes.
    assert!(h.in_flight_len() <= 4, "{} lines", h.in_flight_len());
    assert!(h.in_flight_bytes <= h.cfg.rx_buffer_bytes - h.cfg.estop_reserve_bytes);
}

#[test]
fn an_unreadable_resend_request_does_not_count_its_ok_and_the_probe_finds_the_line() {
    for bad in [
        "Resend: 2x\nok\n",
        "Error:checksum mismatch, Last Line: 1?\nok\n",
    ] {
        let mut h = connected(Dialect::Marlin);
        send(&mut h, 0..2);
        tx(&mut h, t(3));
        feed(&mut h, bad, t(4));
        assert!(accepted(&events(&mut h)).is_empty(), "{bad:?}");
        // The probe goes out at once; its answer says line 2 was refused.
        assert_eq!(
            tx(&mut h, t(4)),
            vec![format!("\n{}", line(PROBE_LINE_NUMBER, "M105"))],
            "{bad:?}"
        );
        feed(
            &mut h,
            "Error:Line Number is not Last Line Number+1, Last Line: 1\nResend: 2\nok\n",
            t(5),
        );
        assert_eq!(tx(&mut h, t(5)), vec![line(2, "G1 X0")], "{bad:?}");
        feed(&mut h, "ok\n", t(6));
        assert_eq!(tx(&mut h, t(6)), vec![line(3, "G1 X1")], "{bad:?}");
        feed(&mut h, "ok\n", t(7));
        assert_eq!(accepted(&events(&mut h)), vec![0, 1], "{bad:?}");
    }
}

/// An error and `ok` with no line of edod's in flight (an operator's macro on another
/// input, say) refuse nothing edod sent: the link goes on.
#[test]
fn an_error_with_no_line_in_flight_stops_nothing() {
    let mut h = connected(Dialect::Klipper);
    feed(&mut h, "!! Move out of range\nok\n", t(3));
    let ev = events(&mut h);
    assert!(
        !ev.iter().any(|e| matches!(e, LineEvent::Stopped { .. })),
        "{ev:?}"
    );
    assert_eq!(h.state(), LinkState::Streaming);
    send(&mut h, 0..1);
    assert_eq!(tx(&mut h, t(4)).len(), 1, "lines still go out");
    feed(&mut h, "ok\n", t(5));
    let ev = events(&mut h);
    assert_eq!(
        accepted(&ev),
        vec![0],
        "the old error does not refuse it: {ev:?}"
    );
    assert_eq!(h.state(), LinkState::Streaming);
}

/// A timed line's lost `ok` (one line in flight, Marlin) is found once overdue for what
/// the line waits for, not after the 10 s timeout: a move waits for the longest of the
/// last `planner_moves` moves accepted, a dwell for all of them and its own length.
#[test]
fn a_timed_lines_lost_ok_is_probed_once_overdue() {
    let mut h = connected(Dialect::Marlin);
    let floor = h.config().ok_overdue_floor_us;
    // Three moves of 40, 100 and 60 ms accepted: the planner may hold 100 ms at once.
    for (tag, us) in [(0, 40_000), (1, 100_000), (2, 60_000)] {
        h.send_timed_line(&format!("G1 X{tag}"), tag, us).unwrap();
        tx(&mut h, t(tag));
        feed(&mut h, "ok\n", t(tag));
    }
    h.send_timed_line("G1 X3", 3, 20_000).unwrap();
    assert_eq!(tx(&mut h, t(10)), vec![line(5, "G1 X3")]);
    // Its `ok` is lost: due 2 x 100 ms + the floor after it went.
    let due = t(10).plus_us(2 * 100_000 + floor);
    assert_eq!(h.next_timeout(), Some(due));
    let before = Micros(due.0 - 1_000);
    h.handle_timeout(before);
    assert!(tx(&mut h, before).is_empty(), "nothing before its time");
    h.handle_timeout(due);
    assert_eq!(
        tx(&mut h, due),
        vec![format!("\n{}", line(PROBE_LINE_NUMBER, "M105"))]
    );
    assert_eq!(h.stats().oks_overdue, 1);
    feed(
        &mut h,
        "Error:Line Number is not Last Line Number+1, Last Line: 5\nResend: 6\nok\n",
        due,
    );
    assert_eq!(accepted(&events(&mut h)), vec![0, 1, 2, 3]);
    // A dwell of 5 s waits for the moves the planner may hold (40 + 100 + 60 + 20 ms)
    // and itself.
    h.send_timed_line("G4 P5000", 4, 5_000_000).unwrap();
    let sent_at = due.plus_us(1_000);
    tx(&mut h, sent_at);
    assert_eq!(
        h.next_timeout(),
        Some(sent_at.plus_us(2 * (220_000 + 5_000_000) + floor))
    );
    // edod's `M400` (a slow command, 900 s untimed) waits like a dwell of no length: a
    // firmware gone silent under it is probed as soon as under a move.
    feed(&mut h, "ok\n", sent_at);
    h.send_timed_line("M400", 5, 0).unwrap();
    let m400_at = sent_at.plus_us(1_000);
    tx(&mut h, m400_at);
    assert_eq!(h.next_timeout(), Some(m400_at.plus_us(2 * 220_000 + floor)));
    // Untimed lines keep the timeouts.
    let mut h = connected(Dialect::Marlin);
    h.send_line("G1 X1", 0).unwrap();
    tx(&mut h, t(0));
    assert_eq!(
        h.next_timeout(),
        Some(t(0).plus_us(h.config().ok_timeout_us))
    );
}

/// A resend request for a line acknowledged further back than the window (one line in
/// flight: any line before the last acknowledged one) is a protocol fault: the link
/// stops naming it and sends nothing again (replayed, 100 acknowledged moves ran twice).
#[test]
fn a_resend_request_for_a_line_long_acknowledged_stops_the_link() {
    let mut h = connected(Dialect::Marlin);
    for tag in 0..10 {
        h.send_line(&format!("G1 X{tag}"), tag).unwrap();
        tx(&mut h, t(tag));
        feed(&mut h, "ok\n", t(tag));
    }
    assert_eq!(accepted(&events(&mut h)).len(), 10);
    feed(&mut h, "Resend: 4\nok\n", t(20));
    let ev = events(&mut h);
    assert!(
        matches!(&ev[..], [LineEvent::Stopped { reason, .. }]
            if reason.contains("line 4") && reason.contains("last acknowledged line 11")),
        "{ev:?}"
    );
    assert!(tx(&mut h, t(21)).is_empty(), "nothing sent again");
}

/// A firmware that answers every handshake line with a resend request: the line is
/// sent again when the handshake or its ok times out (not at once: the request may be for a line sent
/// before a reset), each time an attempt, and the attempts run out (no handshakes at
/// line speed).
#[test]
fn resend_requests_during_the_handshake_count_as_attempts() {
    let mut h = LineHost::new(cfg(Dialect::Marlin));
    h.connect(t(0));
    let mut sent = 0;
    let mut now = t(0);
    for _ in 0..100 {
        sent += tx(&mut h, now).len();
        feed(&mut h, "Resend: 999999\nok\n", now);
        assert!(tx(&mut h, now).is_empty(), "not sent again at once");
        let due = h.next_timeout().unwrap();
        assert!(due > now);
        now = due;
        h.handle_timeout(now);
        if h.state() == LinkState::Lost {
            break;
        }
    }
    assert_eq!(h.state(), LinkState::Lost);
    assert_eq!(sent as u32, h.config().handshake_attempts);
}

/// A machine reset mid-job: Marlin refuses the line still on the wire after its start
/// banner (`Last Line: 0`, `Resend: 1`, `ok`), and that answer comes while `M110` is
/// out. `M110` is not sent again: a second `M110 N0`, its `ok` taken for the first's,
/// runs behind `M115` and sets the firmware's line number back to 0 under the stream
/// ("went back from 1 to 0", a false reset that interrupted the resumed job in
/// `marlin_reset_mid_job_resumes_skipping_nothing`, about 1 run in 18 under load).
#[test]
fn a_line_refused_after_a_reset_does_not_send_m110_again() {
    let mut h = connected(Dialect::Marlin);
    send(&mut h, 0..3);
    tx(&mut h, t(3));
    feed(&mut h, "start\n", t(4));
    assert!(
        matches!(events(&mut h).last(), Some(LineEvent::Reset { .. })),
        "the banner is a reset"
    );
    h.connect(t(5));
    assert_eq!(tx(&mut h, t(5)), vec!["N0 M110 N0*125\n"]);
    feed(
        &mut h,
        "Error:Line Number is not Last Line Number+1, Last Line: 0\nResend: 1\nok\n",
        t(6),
    );
    assert!(tx(&mut h, t(6)).is_empty(), "M110 is not sent again");
    feed(&mut h, "ok\n", t(7));
    assert_eq!(tx(&mut h, t(7)), vec!["N1 M115*39\n"]);
    feed(&mut h, &format!("{MARLIN_ID}\nok\n"), t(8));
    assert_eq!(h.state(), LinkState::Streaming);
    // A handshake line really refused (corrupted on the wire) is sent again once its
    // `ok` is overdue.
    let mut h = LineHost::new(cfg(Dialect::Marlin));
    h.connect(t(0));
    assert_eq!(tx(&mut h, t(0)), vec!["N0 M110 N0*125\n"]);
    feed(
        &mut h,
        "Error:checksum mismatch, Last Line: 0\nResend: 1\nok\n",
        t(1),
    );
    assert!(tx(&mut h, t(1)).is_empty());
    let due = h.next_timeout().unwrap();
    h.handle_timeout(due);
    assert_eq!(tx(&mut h, due), vec!["N0 M110 N0*125\n"]);
    feed(&mut h, "ok\n", due);
    assert_eq!(tx(&mut h, due), vec!["N1 M115*39\n"]);
}
