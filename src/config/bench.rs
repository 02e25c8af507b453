//! The paper's bench in `bfpscope.toml`: a Mad City Labs Nano-Drive (`[stage] backend =
//! "madlib"`), an NI DAQ board as the QPD digitiser (`[qpd] backend = "nidaqmx"`) and the NI
//! board's hardware-timed raster (`[raster] backend = "nidaqmx"`).
//!
//! ```toml
//! [stage]
//! backend = "madlib"
//! library = "/usr/local/lib/libmadlib.so"   # optional; default: the usual names and paths
//! serial = 2847                              # optional; default: the only Nano-Drive attached
//! axes = { x = 1, y = 2, z = 3 }             # Madlib axis numbers (1 = X, 2 = Y, 3 = Z, 4 = A)
//! tolerance_um = 0.05                        # on target when the read-back is this close
//!
//! [qpd]
//! backend = "nidaqmx"
//! library = "/usr/lib/x86_64-linux-gnu/libnidaqmx.so"   # optional
//! device = "Dev1"
//! channels = { sx = "ai0", sy = "ai1", sum = "ai2" }    # or q1..q4
//! range_v = 10.0
//! terminal = "diff"
//! rate_hz = 800000.0
//!
//! [raster]
//! backend = "nidaqmx"
//! ao = { x = "ao0", y = "ao1" }
//! volts_per_um = { x = 0.1333, y = 0.1333 }
//! position = { x = "ai3" }
//! position_volts_per_um = { x = 0.1333 }
//! external_input = "sum"                    # or "replace"; docs/hardware.md §12 says how to check
//! ```
//!
//! Their checks and driver settings live with their families (`instrument/madlib/config.rs`,
//! `instrument/nidaqmx/config.rs`); here: the fake vendor library the tests build, and the
//! config that names it.

/// The fake vendor library the tests build (`libfakebench.so`: Madlib's and NI-DAQmx's
/// symbols over one simulated bench): beside the running binary (`target/<profile>/`), or one
/// folder up (a test binary in `target/<profile>/deps/`).
pub fn fake_bench_library() -> Option<std::path::PathBuf> {
    let name = if cfg!(windows) {
        "fakebench.dll"
    } else if cfg!(target_os = "macos") {
        "libfakebench.dylib"
    } else {
        "libfakebench.so"
    };
    let exe = std::env::current_exe().ok()?;
    let dir = exe.parent()?;
    let found = [
        Some(dir.to_path_buf()),
        Some(dir.join("deps")),
        dir.parent().map(|p| p.to_path_buf()),
    ]
    .into_iter()
    .flatten()
    .map(|d| d.join(name))
    .find(|p: &std::path::PathBuf| p.is_file());
    found
}

/// A `bfpscope.toml` for the fake bench library at `lib` (`bfpscope emulate nidaq`).
pub fn fake_bench_config(lib: &std::path::Path) -> String {
    let l = lib.display().to_string().replace('\\', "/");
    format!(
        r#"# The paper's bench, emulated: a Nano-Drive and an NI PCI-6120 in one fake vendor library
[stage]
backend = "madlib"
library = "{l}"
axes = {{ x = 1, y = 2, z = 3 }}
tolerance_um = 0.05

[qpd]
backend = "nidaqmx"
library = "{l}"
device = "Dev1"
channels = {{ sx = "ai0", sy = "ai1", sum = "ai2" }}
range_v = 10.0
terminal = "diff"
rate_hz = 800000.0

[raster]
backend = "nidaqmx"
ao = {{ x = "ao0", y = "ao1" }}
volts_per_um = {{ x = 0.13333333333333333, y = 0.13333333333333333 }}   # 10 V over 75 µm, exactly
position = {{ x = "ai3" }}
position_volts_per_um = {{ x = 0.13333333333333333 }}
"#
    )
}

#[cfg(test)]
mod tests {
    use super::fake_bench_config;
    use crate::config::{Config, ConfigError};
    use crate::instrument::nidaqmx::raster::ExternalInput;
    use crate::instrument::nidaqmx::NiInputs;

    const BENCH: &str = r#"
[stage]
backend = "madlib"
library = "/usr/local/lib/libmadlib.so"
serial = 2847
axes = { x = 1, y = 2, z = 3 }

[qpd]
backend = "nidaqmx"
library = "/usr/lib/x86_64-linux-gnu/libnidaqmx.so"
device = "Dev1"
channels = { sx = "ai0", sy = "ai1", sum = "ai2" }
range_v = 10.0
terminal = "diff"
rate_hz = 800000.0

[raster]
backend = "nidaqmx"
ao = { x = "ao0", y = "ao1" }
volts_per_um = { x = 0.1333, y = 0.1333 }
position = { x = "ai3" }
position_volts_per_um = { x = 0.1333 }
"#;

    #[test]
    fn the_issue_config_parses_into_driver_settings() {
        let c = Config::from_toml_str(BENCH, "t").unwrap();
        let m = crate::instrument::madlib::config::options(&c.stage).unwrap();
        assert_eq!(m.serial, Some(2847));
        assert_eq!(m.axes, [1, 2, 3]);
        assert_eq!(
            m.library.unwrap().to_str(),
            Some("/usr/local/lib/libmadlib.so")
        );
        let q = crate::instrument::nidaqmx::config::qpd_options(&c.qpd).unwrap();
        assert_eq!(q.device, "Dev1");
        assert_eq!(
            q.inputs,
            NiInputs::Signals {
                sx: "ai0".into(),
                sy: "ai1".into(),
                sum: "ai2".into()
            }
        );
        assert_eq!(q.terminal.daqmx(), 10106);
        assert_eq!(q.rate_hz, 800_000.0);
        let r =
            crate::instrument::nidaqmx::config::raster_options(&c.qpd, c.raster.as_ref().unwrap())
                .unwrap();
        assert_eq!(r.ao, ["ao0".to_string(), "ao1".to_string()]);
        assert_eq!(r.volts_per_um, [0.1333, 0.1333]);
        assert_eq!(r.position, "ai3");
        // and the config round-trips through its TOML
        let again = Config::from_toml_str(&c.to_toml(), "again").unwrap();
        assert_eq!(again, c);
    }

    /// A Nano-Drive settles on its readings: no fixed settle by default (other stages keep
    /// 5 ms); a settle the file gives is kept.
    #[test]
    fn a_nano_drive_has_no_fixed_settle_unless_the_file_gives_one() {
        let c = Config::from_toml_str(BENCH, "t").unwrap();
        assert_eq!(c.stage.settle_s, 0.0);
        let t = BENCH.replace(
            "axes = { x = 1, y = 2, z = 3 }",
            "axes = { x = 1, y = 2, z = 3 }\nsettle_s = 0.01",
        );
        assert_eq!(Config::from_toml_str(&t, "t").unwrap().stage.settle_s, 0.01);
        assert_eq!(Config::default().stage.settle_s, 0.005);
    }

    #[test]
    fn the_emulated_bench_config_is_valid() {
        let c = Config::from_toml_str(
            &fake_bench_config(std::path::Path::new("/t/libfakebench.so")),
            "t",
        )
        .unwrap();
        assert_eq!(
            c.stage.library.as_deref(),
            Some(std::path::Path::new("/t/libfakebench.so"))
        );
        assert_eq!(c.qpd.library, c.stage.library);
        assert!(crate::instrument::nidaqmx::config::raster_options(
            &c.qpd,
            c.raster.as_ref().unwrap()
        )
        .is_ok());
    }

    #[test]
    fn quadrants_are_accepted() {
        let t = BENCH.replace(
            r#"channels = { sx = "ai0", sy = "ai1", sum = "ai2" }"#,
            r#"channels = { q1 = "ai0", q2 = "ai1", q3 = "ai2", q4 = "ai4" }"#,
        );
        let c = Config::from_toml_str(&t, "t").unwrap();
        assert!(matches!(
            crate::instrument::nidaqmx::config::qpd_options(&c.qpd)
                .unwrap()
                .inputs,
            NiInputs::Quadrants(_)
        ));
    }

    fn refused(from: &str, to: &str) -> ConfigError {
        let t = BENCH.replace(from, to);
        assert_ne!(t, BENCH, "{from:?} not in the config");
        Config::from_toml_str(&t, "t").unwrap_err()
    }

    /// `external_input` defaults to MCL's documented "sum", takes "replace", and refuses any
    /// other value naming the key, the value and both choices.
    #[test]
    fn external_input_defaults_to_sum_and_refuses_other_words() {
        let c = Config::from_toml_str(BENCH, "t").unwrap();
        assert_eq!(
            crate::instrument::nidaqmx::config::raster_options(&c.qpd, c.raster.as_ref().unwrap())
                .unwrap()
                .external_input,
            ExternalInput::Sum
        );
        let t = BENCH.replace(
            "position_volts_per_um = { x = 0.1333 }",
            "position_volts_per_um = { x = 0.1333 }\nexternal_input = \"replace\"",
        );
        let c = Config::from_toml_str(&t, "t").unwrap();
        assert_eq!(
            crate::instrument::nidaqmx::config::raster_options(&c.qpd, c.raster.as_ref().unwrap())
                .unwrap()
                .external_input,
            ExternalInput::Replace
        );
        let again = Config::from_toml_str(&c.to_toml(), "again").unwrap();
        assert_eq!(again.raster, c.raster);
        let e = refused(
            "position_volts_per_um = { x = 0.1333 }",
            "position_volts_per_um = { x = 0.1333 }\nexternal_input = \"add\"",
        );
        assert_eq!(e.key, "raster.external_input");
        assert!(
            e.message.starts_with("\"add\": allowed are \"sum\"")
                && e.message.contains("\"replace\""),
            "{e}"
        );
    }

    #[test]
    fn bad_values_name_the_key_the_value_and_what_is_allowed() {
        let e = refused(r#"sy = "ai1""#, r#"sy = "ai0""#);
        assert_eq!(e.key, "qpd.channels");
        assert!(e.message.contains("\"ai0\" is given twice"), "{e}");
        let e = refused(r#"sum = "ai2""#, r#"sum = "a2""#);
        assert_eq!(e.key, "qpd.channels.sum");
        assert!(
            e.message.contains("\"a2\"") && e.message.contains("\"ai0\" … \"ai63\""),
            "{e}"
        );
        let e = refused(r#"terminal = "diff""#, r#"terminal = "single""#);
        assert_eq!(e.key, "qpd.terminal");
        let e = refused("range_v = 10.0", "range_v = -1.0");
        assert!(e.key == "qpd.range_v" && e.message.starts_with("-1"), "{e}");
        let e = refused("rate_hz = 800000.0", "rate_hz = 0.0");
        assert!(
            e.key == "qpd.rate_hz" && e.message.starts_with("0 Hz"),
            "{e}"
        );
        let e = refused(
            "axes = { x = 1, y = 2, z = 3 }",
            "axes = { x = 1, y = 2, z = 5 }",
        );
        assert_eq!(e.key, "stage.axes.z");
        assert!(
            e.message.contains("\"5\"") && e.message.contains("1–4"),
            "{e}"
        );
        let e = refused("serial = 2847", "serial = -1");
        assert_eq!(e.key, "stage.serial");
        let e = refused(r#"position = { x = "ai3" }"#, r#"position = { x = "ai2" }"#);
        assert_eq!(e.key, "raster.position.x");
        assert!(e.message.contains("already a QPD input"), "{e}");
        let e = refused(
            "volts_per_um = { x = 0.1333, y = 0.1333 }",
            "volts_per_um = { x = 0.1333 }",
        );
        assert_eq!(e.key, "raster.volts_per_um.y");
        let e = refused(
            r#"ao = { x = "ao0", y = "ao1" }"#,
            r#"ao = { x = "ao0", y = "ao0" }"#,
        );
        assert_eq!(e.key, "raster.ao.y");
        let e = refused(r#"ao = { x = "ao0", y = "ao1" }"#, "ao = 5");
        assert_eq!(e.key, "raster.ao");
        assert!(
            e.message
                .contains("expected a table of per-axis values { x = …, y = … }"),
            "{e}"
        );
        let e = refused(r#"device = "Dev1""#, r#"device = "Dev1/ai0""#);
        assert_eq!(e.key, "qpd.device");
        let e = refused(r#"sx = "ai0", "#, r#"sx = 1, "#);
        assert_eq!(e.key, "qpd.channels");
        assert!(e.message.contains("not both"), "{e}");
    }

    #[test]
    fn bench_keys_belong_to_their_backends() {
        // each key refused outside its backend (with the message, where it names the backend)
        let refused = [
            (
                "[stage]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\nserial = 3\n[qpd]\nbackend = \"scpi\"\nport = \"/dev/ttyUSB1\"\n",
                "stage.serial",
                Some("only for backend = \"madlib\" (the stage is \"gcs\")"),
            ),
            (
                "[stage]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\n[qpd]\nbackend = \"scpi\"\nport = \"/dev/ttyUSB1\"\nrate_hz = 5.0\n",
                "qpd.rate_hz",
                Some("only for backend = \"nidaqmx\" (the QPD is \"scpi\")"),
            ),
            (
                "[stage]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\n[qpd]\nbackend = \"scpi\"\nport = \"/dev/ttyUSB1\"\nchannels = { sx = \"ai0\", sy = \"ai1\", sum = \"ai2\" }\n",
                "qpd.channels",
                None,
            ),
        ];
        for (t, key, message) in refused {
            let e = Config::from_toml_str(t, "t").unwrap_err();
            assert_eq!(e.key, key);
            if let Some(m) = message {
                assert_eq!(e.message, m);
            }
        }
        // a Red Pitaya's numbers still parse as before
        let t = "[stage]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\n[qpd]\nbackend = \"redpitaya\"\nhost = \"rp\"\nchannels = { sx = 1, sy = 2, sz = 3 }\n";
        let c = Config::from_toml_str(t, "t").unwrap();
        assert_eq!(c.qpd.channels.inputs().sz, Some(3));
    }
}
