//! Every file a protocol writes carries the protocol's name, its arguments, the script's hash and
//! the git revision when available: scans (metadata), templates (JSON), figures (PNG text chunk)
//! and CSV tables (trailing `#` line).

use crate::support::cleanup;

use bfpscope::data::provenance::{png_text, PNG_KEYWORD};
use bfpscope::script::{Settings, Workbench};

#[test]
fn protocol_files_carry_their_provenance() {
    let dir = std::env::temp_dir().join(format!("bfpscope-prov-{}", std::process::id()));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let script = dir.join("calib.rhai");
    let src = r#"
        import "calibrate" as calibrate;
        import "tips" as tips;
        let s = scene();
        s.add_bead(#{x: -3.0, y: 2.0, d_nm: 110.0, n: 1.572});
        s.add_filament(#{points: [[0.0, -3.0], [0.0, 3.0]], d_nm: 80.0, n: 1.41});
        simulate(s);
        let c = calibrate::reference_beads(#{beads: [[-3.0, 2.0]], n: 33, path: out + "/tpl.json"});
        let sc = scan_xy(#{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 41, ny: 41});
        tips::profile(sc, c.template, #{n_obj: 1.41, save: out + "/tip"});
        [c.scans[0], sc.path]
    "#;
    std::fs::write(&script, src).unwrap();
    let (s, _buf) = Settings::captured(dir.join("data"));
    let mut wb = Workbench::new(s);
    wb.set_var("out", dir.display().to_string().into());
    let v = wb.run_file(&script).unwrap_or_else(|e| panic!("{e}"));
    let paths: Vec<String> = v
        .into_array()
        .unwrap()
        .into_iter()
        .map(|p| p.into_string().unwrap())
        .collect();
    let hash = {
        use sha2::Digest;
        let d = sha2::Sha256::digest(src.as_bytes());
        d.iter().map(|b| format!("{b:02x}")).collect::<String>()
    };

    // the calibration scan: metadata names the protocol and its arguments, and the script hash
    let scan = bfpscope::acquire::store::load_scan(std::path::Path::new(&paths[0])).unwrap();
    assert_eq!(scan.meta["protocol"]["name"], "calibrate::reference_beads");
    assert_eq!(scan.meta["protocol"]["args"]["n"], 33);
    assert_eq!(scan.meta["script"]["sha256"], hash.as_str());
    // the scan taken outside any protocol says so
    let plain = bfpscope::acquire::store::load_scan(std::path::Path::new(&paths[1])).unwrap();
    assert!(
        plain.meta["protocol"].is_null(),
        "{}",
        plain.meta["protocol"]
    );

    // the template JSON
    let t: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("tpl.json")).unwrap()).unwrap();
    assert_eq!(
        t["provenance"]["protocol"]["name"],
        "calibrate::reference_beads"
    );
    assert_eq!(t["provenance"]["script"]["sha256"], hash.as_str());
    assert!(t["provenance"].get("git_revision").is_some());

    // the figure: a PNG text chunk that PNG readers keep
    let txt = png_text(&dir.join("tip.png"), PNG_KEYWORD).expect("provenance chunk in the PNG");
    let p: serde_json::Value = serde_json::from_str(&txt).unwrap();
    assert_eq!(p["protocol"]["name"], "tips::profile");
    assert_eq!(p["protocol"]["args"]["opts"]["n_obj"], 1.41);
    // and the PNG still decodes
    let dec = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(dir.join("tip.png")).unwrap(),
    ));
    assert!(dec.read_info().is_ok());

    // the CSV: a trailing comment line; the table still loads
    let csv = std::fs::read_to_string(dir.join("tip.csv")).unwrap();
    let last = csv.lines().last().unwrap();
    assert!(last.starts_with("# bfpscope provenance: "), "{last}");
    assert!(last.contains("tips::profile"), "{last}");
    let (heads, cols) = bfpscope::data::load_csv_table(dir.join("tip.csv")).unwrap();
    assert_eq!(heads, ["arc_um", "d_nm"]);
    assert!(cols[0].len() > 20);
}
