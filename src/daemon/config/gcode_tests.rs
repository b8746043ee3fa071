#[cfg(test)]
mod tests {
    use super::super::Config;

    fn check(machine: &str) -> Result<Config, String> {
        Config::from_toml(machine, "g.toml").map_err(|e| e.to_string())
    }

    fn gcode(table: &str) -> String {
        format!("[machine]\nprotocol = \"gcode\"\n[machine.gcode]\n{table}\n")
    }

    #[test]
    fn defaults_per_firmware() {
        use crate::gcode_link::{MixWriting, Window};
        let c = check(&gcode("firmware = \"marlin\"")).unwrap();
        let g = c.gcode_link().unwrap().unwrap();
        assert_eq!(g.mix, MixWriting::MarlinM163);
        assert_eq!(g.link.window, Window::Auto);
        assert_eq!(g.link.rx_buffer_bytes, 128);
        assert_eq!(g.link.max_bytes_in_flight, 625);
        assert!((g.barrel_area_mm2 - 78.539_816).abs() < 1e-5);
        let c = check(&gcode("firmware = \"rrf\"\nrrf_input = \"Aux\"")).unwrap();
        let g = c.gcode_link().unwrap().unwrap();
        assert_eq!(g.mix, MixWriting::PerDriveE);
        assert_eq!(g.link.rrf_input_name, "Aux");
        let c = check(&gcode("firmware = \"klipper\"\naxes = [\"a\", \"B\"]")).unwrap();
        let g = c.gcode_link().unwrap().unwrap();
        assert_eq!(g.mix, MixWriting::Axes(vec!['A', 'B']));
        let c = check(&gcode(
            "firmware = \"marlin\"\nwindow = \"advanced-ok\"\nrx_buffer_bytes = 1024\n\
             ok_timeout_ms = 2000",
        ))
        .unwrap();
        let g = c.gcode_link().unwrap().unwrap();
        assert_eq!(g.link.window, Window::AdvancedOk);
        assert_eq!(g.link.ok_timeout_us, 2_000_000);
        assert!(check("").unwrap().gcode_link().unwrap().is_none());
    }

    #[test]
    fn impossible_combinations_name_their_key() {
        for (text, key) in [
            (
                gcode("firmware = \"rrf\"\nmix = \"m163\""),
                "machine.gcode.mix",
            ),
            (
                gcode("firmware = \"marlin\"\nmix = \"per-drive-e\""),
                "machine.gcode.mix",
            ),
            (
                gcode("firmware = \"klipper\"\nmix = \"direct\""),
                "machine.gcode.mix",
            ),
            (gcode("firmware = \"klipper\""), "machine.gcode.axes"),
            (
                gcode("firmware = \"klipper\"\naxes = [\"A\"]"),
                "machine.gcode.axes",
            ),
            (
                gcode("firmware = \"klipper\"\naxes = [\"A\", \"E\"]"),
                "machine.gcode.axes",
            ),
            (
                gcode("firmware = \"klipper\"\naxes = [\"A\", \"a\"]"),
                "machine.gcode.axes",
            ),
            (
                gcode("firmware = \"marlin\"\nmix = \"axes\"\naxes = [\"A\", \"I\"]"),
                "machine.gcode.axes",
            ),
            (
                gcode("firmware = \"marlin\"\naxes = [\"A\", \"B\"]"),
                "machine.gcode.axes",
            ),
            (
                gcode("firmware = \"rrf\"\nwindow = 4"),
                "machine.gcode.window",
            ),
            (
                gcode("firmware = \"rrf\"\nwindow = \"advanced-ok\""),
                "machine.gcode.window",
            ),
            (
                gcode("firmware = \"klipper\"\naxes = [\"A\", \"B\"]\nwindow = 20"),
                "machine.gcode.window",
            ),
            (
                gcode("firmware = \"marlin\"\nwindow = \"big\""),
                "machine.gcode.window",
            ),
            (
                gcode("firmware = \"marlin\"\nwindow = 0"),
                "machine.gcode.window",
            ),
            (
                gcode("firmware = \"marlin\"\nrx_buffer_bytes = 32"),
                "machine.gcode.rx_buffer_bytes",
            ),
            (
                gcode("firmware = \"marlin\"\nok_timeout_ms = 5"),
                "machine.gcode.ok_timeout_ms",
            ),
            (
                gcode("firmware = \"marlin\"\nbarrel_area_mm2 = -1.0"),
                "machine.gcode.barrel_area_mm2",
            ),
            (
                gcode("firmware = \"marlin\"\nrrf_input = \"USB\""),
                "machine.gcode.rrf_input",
            ),
            (
                "[machine]\nprotocol = \"gcode\"\n".to_string(),
                "machine.gcode",
            ),
            (
                "[machine.gcode]\nfirmware = \"rrf\"\n".to_string(),
                "machine.gcode",
            ),
        ] {
            let e = check(&text).unwrap_err();
            assert!(e.contains(key), "{text}: {e}");
        }
        let differ = "[[machine.syringes]]\nname = \"A\"\nbarrel_diameter_mm = 10.0\n\
                      capacity_ml = 10.0\n[[machine.syringes]]\nname = \"B\"\n\
                      barrel_diameter_mm = 14.5\ncapacity_ml = 10.0\n";
        let e = check(&format!("{}{differ}", gcode("firmware = \"marlin\""))).unwrap_err();
        assert!(e.contains("machine.syringes"), "{e}");
        let e = check(&format!("{}{differ}", gcode("firmware = \"rrf\""))).unwrap_err();
        assert!(e.contains("machine.gcode.barrel_area_mm2"), "{e}");
        let ok = format!(
            "{}{differ}",
            gcode("firmware = \"rrf\"\nbarrel_area_mm2 = 100.0")
        );
        check(&ok).unwrap();
    }

    #[test]
    fn unknown_keys_are_refused_with_line_and_column() {
        let e = check(&gcode("firmware = \"rrf\"\nwindows = 1")).unwrap_err();
        assert!(e.starts_with("g.toml:5:1"), "{e}");
        assert!(e.contains("windows"), "{e}");
        let e = check(&gcode("firmware = \"smoothie\"")).unwrap_err();
        assert!(e.contains("smoothie"), "{e}");
    }

    #[test]
    fn shipped_gcode_configs_resolve() {
        use crate::gcode_link::Dialect;
        for (f, dialect) in [
            ("config/edod-rrf.toml", Dialect::Rrf),
            ("config/edod-marlin.toml", Dialect::Marlin),
            ("config/edod-klipper.toml", Dialect::Klipper),
        ] {
            let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(f);
            let c = Config::load(&p).unwrap_or_else(|e| panic!("{e}"));
            let g = c.gcode_link().unwrap().unwrap_or_else(|| panic!("{f}"));
            assert_eq!(g.link.dialect, dialect, "{f}");
        }
    }
}
