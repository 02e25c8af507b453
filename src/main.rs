//! `bfpscope`: the command line. `bfpscope` (= `repl`), `run FILE [--set k=v]...`,
//! `eval 'EXPR'`, `test [DIR]`, `docs`, `emulate stage|qpd|pair|kpa101|kpz101|thorlabs|redpitaya`. Exit codes: 0 ok, 1 script error (or failed tests),
//! 2 usage error.

use bfpscope::script::ctx::{err_line, out_line};
use bfpscope::script::{self, show, Settings, Workbench};
use clap::{Parser, Subcommand};
use rhai::Dynamic;
use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;

#[derive(Parser)]
#[command(
    name = "bfpscope",
    version,
    about = "Back-focal-plane interferometric microscopy workbench (Rhai REPL, scans, analysis)"
)]
struct Cli {
    /// Config file (default: $BFPSCOPE_CONFIG, else ./bfpscope.toml if present)
    #[arg(long, global = true, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Session folder for autosaved scans (default: config [session] data_dir, else ./bfpscope_data/YYYY-MM-DD)
    #[arg(long, global = true, value_name = "DIR")]
    data: Option<PathBuf>,
    #[command(subcommand)]
    cmd: Option<Cmd>,
}

#[derive(Subcommand)]
enum Cmd {
    /// Interactive prompt (the default)
    Repl {
        /// Open the live view: a local web page showing every scan while it runs (address printed)
        #[arg(long)]
        view: bool,
        /// Port of the live view (default: a free one); implies --view
        #[arg(long, value_name = "PORT")]
        view_port: Option<u16>,
    },
    /// Run a script file
    Run {
        file: PathBuf,
        /// Script variable, e.g. --set n=64 --set label=bead1 (int, float, bool or string)
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Evaluate an expression and print its value
    Eval { expr: String },
    /// Run the scripted tests (*.rhai) in DIR (default tests/scripts)
    Test { dir: Option<PathBuf> },
    /// Regenerate the API reference from the binding declarations
    Docs {
        #[arg(long, default_value = "docs/api.md")]
        out: PathBuf,
        /// Only check that the file is up to date (exit 1 if stale)
        #[arg(long)]
        check: bool,
    },
    /// Serve device emulators on pseudo-terminals (try the hardware path without hardware):
    /// prints their paths and a bfpscope.toml snippet, serves until Ctrl-C
    Emulate {
        /// `stage` (alias `gcs`: PI GCS 2.0), `qpd` (SCPI digitiser), `pair` (both, sharing the stage position),
        /// `kpz101` (three Thorlabs piezo cubes), `kpa101` (Thorlabs position aligner), `thorlabs` (both)
        /// `redpitaya` (a GCS stage and a Red Pitaya STEMlab on a loopback TCP port) or `nidaq`
        /// (alias `bench`: prints the fake Madlib + NI-DAQmx library's path and a config)
        device: String,
        /// Scene the QPD images, as JSON (a scan's `meta.scene`); default: a 110 nm polystyrene bead at the origin
        #[arg(long, value_name = "FILE")]
        scene: Option<PathBuf>,
        /// Serve the GCS stage on this TCP address instead of a pseudo-terminal, as a PI
        /// controller's port 50000 (`127.0.0.1:0`: a free loopback port; the address is printed)
        #[arg(long, value_name = "ADDR")]
        tcp: Option<String>,
        /// The emulated stage answers a query naming several axes for the first one only
        #[arg(long)]
        one_axis_per_query: bool,
        /// `redpitaya`: serve the board's SCPI server on this loopback TCP port (default: a free
        /// port, printed; a real board listens on 5000)
        #[arg(long, value_name = "N")]
        port: Option<u16>,
        /// `redpitaya`: 2 fast inputs (STEMlab 125-14, default) or 4 (its 4-input model, Sz on IN3)
        #[arg(long, value_name = "N")]
        inputs: Option<usize>,
        /// Baud rate of the modelled serial links (10 bits per byte, both ways); `max` (or 0):
        /// the pseudo-terminal's full speed
        #[arg(long, default_value = "115200", value_name = "RATE")]
        baud: String,
        /// Reply latency of the modelled links, ms (from the end of a command to the start of
        /// its reply; a USB-serial bridge adds about 1 ms)
        #[arg(long, default_value_t = 1.0, value_name = "MS")]
        latency_ms: f64,
    },
    /// Measure what accuracy costs in time (every knob, instrument-time trade-off, benchmark
    /// summary) and write OUT/accuracy.md and OUT/accuracy/*.png
    Accuracy {
        /// Short sweeps (CI; under a minute in a release build)
        #[arg(long)]
        quick: bool,
        #[arg(long, default_value = "docs")]
        out: PathBuf,
        /// Criterion results to summarise (default target/criterion when present)
        #[arg(long, value_name = "DIR")]
        criterion: Option<PathBuf>,
        /// The truth sweep's section to include (`bfpscope sweep --markdown FILE`; default
        /// target/sweep.md when present)
        #[arg(long, value_name = "FILE")]
        sweep: Option<PathBuf>,
    },
    /// The truth sweep: random scenes on the simulator, every estimator against the truth;
    /// prints per estimator its cases, coverage of 1σ/2σ, flags and unflagged outliers
    Sweep {
        /// Scenes per estimator family
        #[arg(long, default_value_t = 200)]
        n: usize,
        /// Seed of the scene draw (any seed must pass)
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Print one JSON object instead of the table
        #[arg(long)]
        json: bool,
        /// Run only these families (beads, fibril, focus, microtubule, maxsens; comma-separated; default
        /// all). A family's scenes are the same whichever others run
        #[arg(long, value_delimiter = ',')]
        family: Vec<String>,
        /// Rerun one scene of a BFPSCOPE_SWEEP_DUMP line (its `scene` JSON) and tell it in words
        #[arg(long, value_name = "SCENE_JSON")]
        replay: Option<String>,
        /// Also write the sweep's section of docs/accuracy.md (the command, the table, the
        /// outliers) to this file; `bfpscope accuracy --sweep FILE` includes it
        #[arg(long, value_name = "FILE")]
        markdown: Option<PathBuf>,
    },
}

/// `bfpscope docs`: rewrite the stop rule's copies in the docs from `acquire::stop_rule`
/// (`check`: only say which are stale, exit 1). Paths are relative to the working directory
/// (the repository root).
fn stop_rule_docs(check: bool) -> Result<(), ExitCode> {
    use bfpscope::acquire::stop_rule::{with_stop_rule, STOP_RULE_DOCS};
    let mut stale = false;
    for (path, want) in STOP_RULE_DOCS {
        let cur = std::fs::read_to_string(path)
            .map_err(|e| usage_error(&format!("docs: {path}: {e}")))?;
        let (new, n) =
            with_stop_rule(&cur).map_err(|e| usage_error(&format!("docs: {path}: {e}")))?;
        if n != want {
            eprintln!("{path}: {n} copies of the stop rule, {want} expected (`<!-- stop-rule:full -->` … `<!-- /stop-rule -->`)");
            stale = true;
        } else if new != cur {
            if check {
                eprintln!("{path}: the stop rule is stale: run `bfpscope docs`");
                stale = true;
            } else {
                std::fs::write(path, new)
                    .map_err(|e| usage_error(&format!("docs: {path}: {e}")))?;
                println!("wrote the stop rule into {path}");
            }
        }
    }
    if stale {
        return Err(ExitCode::from(1));
    }
    Ok(())
}

fn usage_error(msg: &str) -> ExitCode {
    err_line(&format!("error: {msg}"));
    ExitCode::from(2)
}

/// `key=value` → (key, value as int, float, bool or string).
fn parse_set(s: &str) -> Result<(String, Dynamic), String> {
    let (k, v) = s
        .split_once('=')
        .ok_or_else(|| format!("--set {s}: expected KEY=VALUE"))?;
    let k = k.trim();
    let valid = !k.is_empty()
        && k.chars()
            .next()
            .is_some_and(|c| c.is_alphabetic() || c == '_')
        && k.chars().all(|c| c.is_alphanumeric() || c == '_');
    if !valid {
        return Err(format!("--set {s}: `{k}` is not a valid variable name"));
    }
    let d = if let Ok(i) = v.parse::<i64>() {
        Dynamic::from(i)
    } else if let Ok(f) = v.parse::<f64>() {
        Dynamic::from(f)
    } else if let Ok(b) = v.parse::<bool>() {
        Dynamic::from(b)
    } else {
        Dynamic::from(v.to_string())
    };
    Ok((k.to_string(), d))
}

/// Ctrl-C sets the shared flag (scans stop at the next point, scripts are interrupted); three
/// presses while the flag is still set end the process.
fn install_ctrlc(flag: Arc<AtomicBool>) {
    static PRESSES: AtomicUsize = AtomicUsize::new(0);
    let _ = ctrlc::set_handler(move || {
        if flag.swap(true, Ordering::SeqCst) {
            if PRESSES.fetch_add(1, Ordering::SeqCst) >= 2 {
                eprintln!("\nbfpscope: interrupted three times, exiting");
                std::process::exit(130);
            }
        } else {
            PRESSES.store(0, Ordering::SeqCst);
        }
    });
}

/// Connect what the config names (no config: the simulated instrument with an empty scene;
/// `simulate(scene)` puts objects in front of it). A device that cannot be opened is an
/// error naming it (exit 1).
fn connect_default(wb: &Workbench) -> Result<(), ExitCode> {
    let cfg = wb.ctx.settings.config.clone().unwrap_or_default();
    match script::motion::connect_config(&wb.ctx, &cfg) {
        Ok(_) => Ok(()),
        Err(e) => {
            err_line(&format!("error: {e}"));
            Err(ExitCode::from(1))
        }
    }
}

/// `bfpscope emulate stage|qpd|pair|kpa101|kpz101|thorlabs [--scene FILE]`: emulators whose QPD images a simulated
/// scene at the emulated stage position.
fn emulate(
    device: &str,
    scene: Option<&std::path::Path>,
    opts: &bfpscope::instrument::emulator::EmulateOptions,
) -> ExitCode {
    use bfpscope::instrument::sim::{scene::Scene, Renderer, SimConfig};
    if device == "nidaq" || device == "bench" {
        // the paper's bench is a fake vendor library, not a served port: print where it is
        return match bfpscope::config::bench::fake_bench_library() {
            Some(lib) => {
                out_line(&format!(
                    "fake Madlib + NI-DAQmx library (a Nano-Drive and a PCI-6120 imaging a 110 nm bead): {}",
                    lib.display()
                ));
                out_line("bfpscope.toml:");
                out_line(&bfpscope::config::bench::fake_bench_config(&lib));
                ExitCode::SUCCESS
            }
            None => usage_error(
                "emulate nidaq: the fake bench library (libfakebench.so) is not beside the binary: build it with \
                 `cargo build --workspace` (the same profile as bfpscope)",
            ),
        };
    }
    if ![
        "stage",
        "gcs",
        "qpd",
        "pair",
        "both",
        "kpa101",
        "kpz101",
        "thorlabs",
        "redpitaya",
    ]
    .contains(&device)
    {
        return usage_error(&format!(
            "emulate: unknown device `{device}` (expected `stage` (alias `gcs`), `qpd`, `pair`, `kpa101`, \
             `kpz101`, `thorlabs`, `redpitaya` or `nidaq`)"
        ));
    }
    let scene = match scene {
        None => script::motion::reference_bead_scene(),
        Some(p) => {
            let parsed = std::fs::read_to_string(p)
                .map_err(|e| e.to_string())
                .and_then(|t| serde_json::from_str::<Scene>(&t).map_err(|e| e.to_string()));
            match parsed {
                Ok(s) => s,
                Err(e) => return usage_error(&format!("emulate: --scene {}: {e}", p.display())),
            }
        }
    };
    let optics = bfpscope::optics::Optics::default();
    let renderer = match Renderer::checked(
        &optics,
        &scene,
        bfpscope::optics::template::TemplateSpec::default(),
    ) {
        Ok(r) => std::sync::Arc::new(r),
        Err(e) => return usage_error(&format!("emulate: scene: {e}")),
    };
    out_line(&format!(
        "scene: {} bead(s), {} filament(s), imaged by the QPD emulator at the emulated stage position",
        scene.beads.len(),
        scene.filaments.len()
    ));
    match bfpscope::instrument::emulator::run_emulator_cli_sim(
        device,
        renderer,
        &SimConfig::default(),
        opts,
    ) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            err_line(&format!("error: emulate: {e}"));
            ExitCode::from(1)
        }
    }
}

/// The session's settings from the command line: the config (`--config`, else
/// `$BFPSCOPE_CONFIG`, else `./bfpscope.toml`) and the data folder (`--data`, else the
/// config's, else today's folder); a config that does not load is a usage error.
fn settings_from(cli: &Cli) -> Result<Settings, ExitCode> {
    let mut settings = Settings {
        progress: std::io::stderr().is_terminal(),
        ..Settings::default()
    };
    // --config, else $BFPSCOPE_CONFIG, else ./bfpscope.toml; parsed once, [safety] included
    let config_path = cli
        .config
        .clone()
        .or_else(|| {
            std::env::var_os(bfpscope::config::ENV_VAR)
                .filter(|p| !p.is_empty())
                .map(PathBuf::from)
        })
        .or_else(|| Some(PathBuf::from(bfpscope::config::DEFAULT_FILE)).filter(|p| p.exists()));
    if let Some(p) = config_path {
        let c = match bfpscope::config::Config::load(&p) {
            Ok(c) => c,
            Err(e) => return Err(usage_error(&e.to_string())),
        };
        if let Err(e) = settings.apply_config(c, Some(p.clone())) {
            return Err(usage_error(&format!("{}: {e}", p.display())));
        }
    }
    if let Some(d) = &cli.data {
        settings.data_dir = d.clone();
    } else if settings.data_dir == std::path::Path::new(bfpscope::data::session::DEFAULT_ROOT) {
        // no --data, no [session] data_dir: today's folder, ./bfpscope_data/YYYY-MM-DD/
        settings.data_dir = bfpscope::data::session::Session::default_dir(
            std::path::Path::new(bfpscope::data::session::DEFAULT_ROOT),
            std::time::SystemTime::now(),
        );
    }
    Ok(settings)
}

/// `bfpscope test [DIR]`: the scripted tests of a folder (default `tests/scripts`).
fn test_cmd(dir: Option<PathBuf>, settings: &Settings) -> ExitCode {
    let dir = dir.unwrap_or_else(|| PathBuf::from("tests/scripts"));
    if !dir.is_dir() {
        return usage_error(&format!("test: {}: no such folder", dir.display()));
    }
    // a folder without any test is an error, as a missing folder is
    match script::testing::test_files(&dir) {
        Ok(f) if f.is_empty() => {
            return usage_error(&format!(
                "test: {}: no test in the folder (no *.rhai file)",
                dir.display()
            ))
        }
        Err(e) => return usage_error(&format!("test: {}: {e}", dir.display())),
        Ok(_) => {}
    }
    let mut out = std::io::stdout();
    match script::testing::run_dir(&dir, settings, &mut out) {
        Ok(results) if results.iter().all(|r| r.passed) => ExitCode::SUCCESS,
        Ok(_) => ExitCode::from(1),
        Err(e) => usage_error(&format!("test: {}: {e}", dir.display())),
    }
}

/// `bfpscope sweep`: the truth sweep (`accuracy::sweep::cli`), or one scene of its dump rerun
/// and told in words (`--replay`).
fn sweep_cmd(
    opts: bfpscope::accuracy::sweep::SweepOptions,
    json: bool,
    replay: Option<String>,
    markdown: Option<PathBuf>,
) -> ExitCode {
    let Some(scene) = replay else {
        return bfpscope::accuracy::sweep::cli(&opts, json, markdown.as_deref());
    };
    match bfpscope::accuracy::sweep::replay(&scene) {
        Ok(s) => {
            print!("{s}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: sweep: {e}");
            ExitCode::from(2)
        }
    }
}

/// `bfpscope accuracy`: the accuracy-vs-time report.
fn accuracy_cmd(
    quick: bool,
    out: PathBuf,
    criterion: Option<PathBuf>,
    sweep: Option<PathBuf>,
) -> ExitCode {
    let opts = bfpscope::accuracy::report::ReportOptions {
        quick,
        out,
        criterion: criterion.or_else(|| Some(PathBuf::from("target/criterion"))),
        sweep: sweep.or_else(|| Some(PathBuf::from("target/sweep.md"))),
        verbose: true,
        targeted: Some(bfpscope::script::targeted_study),
    };
    match bfpscope::accuracy::report::run(&opts) {
        Ok(r) => {
            println!("wrote {} ({:.0} s)", r.markdown.display(), r.seconds);
            ExitCode::SUCCESS
        }
        Err(e) => {
            err_line(&format!("error: accuracy: {e}"));
            ExitCode::from(1)
        }
    }
}

/// `bfpscope docs [--check]`: write docs/api.md (and the stop rule's prose), or check them.
fn docs_cmd(out: PathBuf, check: bool) -> ExitCode {
    let text = script::registry::api_markdown(&script::all_docs());
    if let Err(code) = stop_rule_docs(check) {
        return code;
    }
    if check {
        let cur = std::fs::read_to_string(&out).unwrap_or_default();
        if cur == text {
            println!("{} is up to date", out.display());
            ExitCode::SUCCESS
        } else {
            eprintln!("{} is stale: run `bfpscope docs`", out.display());
            ExitCode::from(1)
        }
    } else {
        if let Some(d) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
            let _ = std::fs::create_dir_all(d);
        }
        match std::fs::write(&out, text) {
            Ok(()) => {
                println!("wrote {}", out.display());
                ExitCode::SUCCESS
            }
            Err(e) => usage_error(&format!("docs: {}: {e}", out.display())),
        }
    }
}

fn main() -> ExitCode {
    bfpscope::tune_allocator();
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            let code = if e.use_stderr() { 2 } else { 0 };
            let _ = e.print();
            return ExitCode::from(code);
        }
    };
    let settings = match settings_from(&cli) {
        Ok(s) => s,
        Err(code) => return code,
    };
    if let Some(Cmd::Emulate {
        device,
        scene,
        tcp,
        one_axis_per_query,
        port,
        inputs,
        baud,
        latency_ms,
    }) = &cli.cmd
    {
        let link = match bfpscope::instrument::emulator::parse_link(baud, *latency_ms) {
            Ok(l) => l,
            Err(e) => return usage_error(&e),
        };
        // the emulators install their own Ctrl-C handler (stop serving)
        let opts = bfpscope::instrument::emulator::EmulateOptions {
            tcp: tcp.clone(),
            one_axis_per_query: *one_axis_per_query,
            port: *port,
            inputs: inputs.unwrap_or(0),
            link,
            along: None,
        };
        return emulate(device, scene.as_deref(), &opts);
    }
    install_ctrlc(settings.abort.clone());
    // Scans are autosaved in the session folder: a folder they cannot be saved in is refused
    // before anything runs (the prompt and script runs; `eval` only warns).
    if let Some(cmd) = &cli.cmd {
        let strict = matches!(cmd, Cmd::Repl { .. } | Cmd::Run { .. });
        if matches!(cmd, Cmd::Repl { .. } | Cmd::Run { .. } | Cmd::Eval { .. }) {
            if let Err(e) = bfpscope::data::session::Session::check_writable(&settings.data_dir) {
                if strict {
                    return usage_error(&format!("{e} (give another with --data DIR)"));
                }
                err_line(&format!("warning: {e} (give another with --data DIR)"));
            }
        }
    } else if let Err(e) = bfpscope::data::session::Session::check_writable(&settings.data_dir) {
        return usage_error(&format!("{e} (give another with --data DIR)"));
    }

    let default_cmd = Cmd::Repl {
        view: false,
        view_port: None,
    };
    match cli.cmd.unwrap_or(default_cmd) {
        Cmd::Repl { view, view_port } => {
            let wb = Workbench::new(settings);
            if let Err(code) = connect_default(&wb) {
                return code;
            }
            if view || view_port.is_some() {
                match script::view::start_view(&wb.ctx, "127.0.0.1", view_port.unwrap_or(0)) {
                    Ok(url) => err_line(&format!("live view: {url}")),
                    Err(e) => return usage_error(&e),
                }
            }
            ExitCode::from(bfpscope::repl::run(wb, bfpscope::repl::default_history()) as u8)
        }
        Cmd::Run { file, set } => {
            if !file.is_file() {
                return usage_error(&format!("run: {}: no such script file", file.display()));
            }
            let mut wb = Workbench::new(settings);
            if let Err(code) = connect_default(&wb) {
                return code;
            }
            for s in &set {
                match parse_set(s) {
                    Ok((k, v)) => wb.set_var(&k, v),
                    Err(e) => return usage_error(&e),
                }
            }
            match wb.run_file(&file) {
                Ok(_) => ExitCode::SUCCESS,
                Err(e) => {
                    err_line(&format!("error: {e}"));
                    ExitCode::from(1)
                }
            }
        }
        Cmd::Eval { expr } => {
            let mut wb = Workbench::new(settings);
            if let Err(code) = connect_default(&wb) {
                return code;
            }
            match wb.eval_source("eval", &expr) {
                Ok(v) => {
                    if !v.is_unit() {
                        out_line(&show(&v));
                    }
                    ExitCode::SUCCESS
                }
                Err(e) => {
                    err_line(&format!("error: {e}"));
                    ExitCode::from(1)
                }
            }
        }
        Cmd::Test { dir } => test_cmd(dir, &settings),
        Cmd::Emulate { .. } => unreachable!("handled before the Ctrl-C handler is installed"),
        Cmd::Accuracy {
            quick,
            out,
            criterion,
            sweep,
        } => accuracy_cmd(quick, out, criterion, sweep),
        Cmd::Sweep {
            n,
            seed,
            json,
            family,
            replay,
            markdown,
        } => sweep_cmd(
            bfpscope::accuracy::sweep::SweepOptions {
                n,
                seed,
                families: family,
            },
            json,
            replay,
            markdown,
        ),
        Cmd::Docs { out, check } => docs_cmd(out, check),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn set_values_parse_by_type() {
        assert_eq!(parse_set("n=64").unwrap().1.as_int().unwrap(), 64);
        assert_eq!(parse_set("dwell=0.5").unwrap().1.as_float().unwrap(), 0.5);
        assert!(parse_set("snake=true").unwrap().1.as_bool().unwrap());
        assert_eq!(parse_set("label=bead 1").unwrap().1.to_string(), "bead 1");
        assert_eq!(
            parse_set("1x=3").unwrap_err(),
            "--set 1x=3: `1x` is not a valid variable name"
        );
        assert_eq!(
            parse_set("novalue").unwrap_err(),
            "--set novalue: expected KEY=VALUE"
        );
    }
}
