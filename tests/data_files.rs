//! Images and profiles (statistics, slicing, arithmetic), scan files (.npz, also read back with
//! numpy when it is installed), the session store, TIFF and CSV round trips.

use crate::support::cleanup;

use bfpscope::data::{
    load_csv_profile, load_csv_table, load_scan, load_tiff, save_csv_profile, save_csv_table,
    save_scan, save_tiff, DataError, Image, Profile, Scan, ScanStatus, Session,
};
use ndarray::{array, Array2};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A fresh, empty directory for one test; removed when the test passes, kept for inspection
/// when it fails.
struct TestDir(PathBuf);

impl TestDir {
    fn join(&self, p: impl AsRef<Path>) -> PathBuf {
        self.0.join(p)
    }
}

impl std::ops::Deref for TestDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for TestDir {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl Drop for TestDir {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

fn test_dir(name: &str) -> TestDir {
    let d = std::env::temp_dir().join(format!("bfpscope-data-{}-{name}", std::process::id()));
    cleanup::at_exit(&d);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    TestDir(d)
}

fn files_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

fn bits(a: &[f64]) -> Vec<u64> {
    a.iter().map(|v| v.to_bits()).collect()
}

fn img_bits(i: &Image) -> Vec<u64> {
    i.data.iter().map(|v| v.to_bits()).collect()
}

/// 2x3 image: x = [-1, 0, 1], y = [10, 10.5].
fn small() -> Image {
    Image::new(
        array![[1.0, f64::NAN, 3.0], [-4.0, 5.0, 6.0]],
        vec![-1.0, 0.0, 1.0],
        vec![10.0, 10.5],
    )
}

// ------------------------------------------------------------------ image operations

#[test]
fn statistics_skip_nan() {
    let img = small();
    // finite values: 1, 3, -4, 5, 6 -> mean 11/5, population variance
    let vals = [1.0, 3.0, -4.0, 5.0, 6.0];
    let mean = 11.0 / 5.0;
    let var = vals.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / 5.0;
    assert_eq!(img.min().unwrap(), -4.0);
    assert_eq!(img.max().unwrap(), 6.0);
    assert_eq!(img.abs_max().unwrap(), 6.0);
    assert!((img.mean().unwrap() - mean).abs() < 1e-15);
    assert!((img.std().unwrap() - var.sqrt()).abs() < 1e-14);
    assert_eq!(img.nan_count(), 1);
    assert_eq!(img.summary().unwrap().count, 5);
    let neg = img.mul_scalar(-2.0).unwrap();
    assert_eq!(
        neg.abs_max().unwrap(),
        12.0,
        "abs_max sees the negative extreme"
    );
}

#[test]
fn statistics_of_all_nan_image_are_errors() {
    let img = Image::new(
        Array2::from_elem((2, 2), f64::NAN),
        vec![0.0, 1.0],
        vec![0.0, 1.0],
    );
    for r in [img.min(), img.max(), img.abs_max(), img.mean(), img.std()] {
        let e = r.unwrap_err();
        assert!(matches!(e, DataError::AllNaN { count: 4, .. }), "{e:?}");
        assert!(e.to_string().contains("all 4 values are NaN"), "{e}");
    }
    let p = Profile::new(vec![], vec![]);
    assert!(matches!(p.max().unwrap_err(), DataError::Empty(_)));
}

#[test]
fn rows_and_columns_are_profiles_with_axes() {
    let img = small().with_axis_names("x", "z");
    let r = img.row(1).unwrap();
    assert_eq!(r.v, vec![-4.0, 5.0, 6.0]);
    assert_eq!(r.t, vec![-1.0, 0.0, 1.0]);
    assert_eq!(r.t_name, "x");
    let c = img.col(2).unwrap();
    assert_eq!(c.v, vec![3.0, 6.0]);
    assert_eq!(c.t, vec![10.0, 10.5]);
    assert_eq!(c.t_name, "z");
    assert_eq!(r.max().unwrap(), 6.0);
    assert_eq!(c.mean().unwrap(), 4.5);
}

#[test]
fn out_of_range_indices_name_index_and_range() {
    let img = small();
    let e = img.row(2).unwrap_err().to_string();
    assert_eq!(e, "row index 2 is out of range: valid indices are 0..=1");
    let e = img.col(-1).unwrap_err().to_string();
    assert_eq!(
        e,
        "column index -1 is out of range: valid indices are 0..=2"
    );
    let e = img.col(3).unwrap_err().to_string();
    assert_eq!(e, "column index 3 is out of range: valid indices are 0..=2");
    assert!(img.row(0).is_ok());
}

#[test]
fn crop_by_axis_range() {
    let x: Vec<f64> = (0..5).map(|j| -1.0 + 0.5 * j as f64).collect();
    let y: Vec<f64> = (0..4).map(|i| 0.1 * i as f64).collect(); // 0, 0.1, 0.2, 0.30000000000000004
    let data = Array2::from_shape_fn((4, 5), |(i, j)| (10 * i + j) as f64);
    let img = Image::new(data, x, y);
    let c = img.crop((-0.5, 0.5), (0.3, 0.1)).unwrap(); // y bounds reversed; 0.3 must include 0.30000000000000004
    assert_eq!(c.shape(), (3, 3));
    assert_eq!(c.x, vec![-0.5, 0.0, 0.5]);
    assert_eq!(c.data[[0, 0]], 11.0);
    assert_eq!(c.data[[2, 2]], 33.0);
    let e = img.crop((2.0, 3.0), (0.0, 1.0)).unwrap_err().to_string();
    assert!(e.contains("x_range") && e.contains("-1..1"), "{e}");
    let e = img
        .crop((f64::NAN, 1.0), (0.0, 1.0))
        .unwrap_err()
        .to_string();
    assert!(e.contains("finite"), "{e}");
}

#[test]
fn arithmetic_checks_shapes_and_scalars() {
    let a = Image::new(
        array![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]],
        vec![0.0, 1.0, 2.0],
        vec![0.0, 1.0],
    );
    let b = a.mul_scalar(10.0).unwrap();
    assert_eq!(
        a.add(&b).unwrap().data,
        array![[11.0, 22.0, 33.0], [44.0, 55.0, 66.0]]
    );
    assert_eq!(
        b.sub(&a).unwrap().data,
        array![[9.0, 18.0, 27.0], [36.0, 45.0, 54.0]]
    );
    assert_eq!(
        a.mul(&a).unwrap().data,
        array![[1.0, 4.0, 9.0], [16.0, 25.0, 36.0]]
    );
    assert_eq!(a.add_scalar(1.0).unwrap().data[[1, 2]], 7.0);
    assert_eq!(a.sub_scalar(1.0).unwrap().data[[0, 0]], 0.0);
    assert_eq!(a.div_scalar(4.0).unwrap().data[[0, 1]], 0.5);
    let t = Image::new(Array2::zeros((3, 2)), vec![0.0, 1.0], vec![0.0, 1.0, 2.0]);
    let e = a.sub(&t).unwrap_err().to_string();
    assert_eq!(
        e,
        "image sub: shapes differ: left is 2x3 (rows x cols), right is 3x2"
    );
    let e = a.div_scalar(0.0).unwrap_err().to_string();
    assert!(e.contains("division by zero"), "{e}");
    let e = a.mul_scalar(f64::NAN).unwrap_err().to_string();
    assert!(e.contains("finite"), "{e}");
    assert_eq!(
        a.add(&b).unwrap().x,
        a.x,
        "result keeps the left operand's axes"
    );
}

#[test]
fn display_is_one_readable_line() {
    let s = small().to_string();
    assert_eq!(
        s,
        "Image 2x3 (rows x cols), x -1..1 µm, y 10..10.5 µm, min -4, max 6, 1 NaN"
    );
    let p = small().row(0).unwrap().to_string();
    assert_eq!(p, "Profile 3 points, x -1..1 µm, min 1, max 3, 1 NaN");
}

#[test]
fn try_new_validates_user_input() {
    let e = Image::try_new(Array2::zeros((2, 3)), vec![0.0, 1.0], vec![0.0, 1.0])
        .unwrap_err()
        .to_string();
    assert!(e.contains("`x`") && e.contains("(3)"), "{e}");
    let e = Image::try_new(Array2::zeros((2, 2)), vec![0.0, 0.0], vec![0.0, 1.0])
        .unwrap_err()
        .to_string();
    assert!(e.contains("monotonic"), "{e}");
    let e = Image::try_new(Array2::zeros((0, 2)), vec![0.0, 1.0], vec![])
        .unwrap_err()
        .to_string();
    assert!(e.contains("at least one row"), "{e}");
    assert!(Image::try_new(Array2::zeros((1, 2)), vec![1.0, 0.0], vec![5.0]).is_ok());
}

// ------------------------------------------------------------------ scans as .npz

/// An aborted XZ scan with NaN pixels, -0.0, subnormal and extreme values, non-square.
fn aborted_scan() -> Scan {
    let (rows, cols) = (5, 7);
    let x: Vec<f64> = (0..cols).map(|j| -0.3 + 0.1 * j as f64).collect();
    let z: Vec<f64> = (0..rows).map(|i| 1.0 + 0.05 * i as f64).collect();
    let mut sx = Array2::from_shape_fn((rows, cols), |(i, j)| {
        ((i * cols + j) as f64 * 0.37).sin() * 1e-3
    });
    let sy = Array2::from_shape_fn((rows, cols), |(i, j)| {
        (i as f64 - 2.0) * (j as f64 + 0.1) / 3.0
    });
    let mut sz = Array2::from_shape_fn((rows, cols), |(i, j)| 2.5 + 0.01 * (i + j) as f64);
    sx[[0, 0]] = -0.0;
    sx[[0, 1]] = 5e-324; // smallest subnormal
    sx[[0, 2]] = f64::MAX;
    sz[[0, 0]] = 0.1 + 0.2; // 0.30000000000000004
    let mut sy = sy;
    // the scan stopped in row 3: the rest is unmeasured
    for i in 3..rows {
        for j in 0..cols {
            if i > 3 || j >= 4 {
                sx[[i, j]] = f64::NAN;
                sy[[i, j]] = f64::NAN;
                sz[[i, j]] = f64::NAN;
            }
        }
    }
    let mk = |d| Image::new(d, x.clone(), z.clone()).with_axis_names("x", "z");
    Scan {
        sx: mk(sx),
        sy: mk(sy),
        sz: mk(sz),
        status: ScanStatus::Aborted,
        meta: json!({
            "plan": {"kind": "scan_xz", "x": [-0.3, 0.3], "z": [1.0, 1.2], "nx": 7, "nz": 5, "dwell": 0.001},
            "optics": {"wavelength_nm": 1064.0, "n_medium": 1.33},
            "script": {"path": "scripts/demo.rhai", "sha256": "00ff"},
            "time": "2026-11-21T16:00:00Z",
            "note": "µm ünïcode ✓"
        }),
        raw: Vec::new(),
        flags: Default::default(),
    }
}

fn assert_same_scan(a: &Scan, b: &Scan) {
    for (name, p, q) in [
        ("sx", &a.sx, &b.sx),
        ("sy", &a.sy, &b.sy),
        ("sz", &a.sz, &b.sz),
    ] {
        assert_eq!(p.shape(), q.shape(), "{name} shape");
        assert_eq!(img_bits(p), img_bits(q), "{name} pixels bit for bit");
        assert_eq!(bits(&p.x), bits(&q.x), "{name} x axis");
        assert_eq!(bits(&p.y), bits(&q.y), "{name} y axis");
        assert_eq!(
            (&p.x_name, &p.y_name),
            (&q.x_name, &q.y_name),
            "{name} axis names"
        );
    }
    assert_eq!(a.status, b.status);
    assert_eq!(a.meta, b.meta);
}

#[test]
fn npz_round_trip_is_bit_for_bit() {
    let dir = test_dir("npz-roundtrip");
    let scan = aborted_scan();
    let path = dir.join("scan.npz");
    save_scan(&path, &scan).unwrap();
    let back = load_scan(&path).unwrap();
    assert_same_scan(&scan, &back);
    assert!(
        back.sx.data[[0, 0]].is_sign_negative() && back.sx.data[[0, 0]] == 0.0,
        "-0.0 kept"
    );
    assert_eq!(back.sx.nan_count(), 3 + 7);
    assert_eq!(back.status, ScanStatus::Aborted);
    assert_eq!(back.sx.y_name, "z");
    // no temporary files left behind
    assert_eq!(files_in(&dir), vec!["scan.npz"]);
}

#[test]
fn scan_display_is_one_line() {
    let s = aborted_scan().to_string();
    assert!(
        s.starts_with("Scan (aborted) 5x7 (rows x cols), x -0.3..0.3 µm, z 1..1.2 µm"),
        "{s}"
    );
    assert!(s.ends_with(", 10 unmeasured pixels"), "{s}");
    assert!(!s.contains('\n'));
}

#[test]
fn npz_round_trip_of_non_object_metadata() {
    let dir = test_dir("npz-meta");
    for (k, meta) in [
        serde_json::Value::Null,
        json!([1, 2, 3]),
        json!({"status": "laser ok"}),
    ]
    .into_iter()
    .enumerate()
    {
        let mut scan = aborted_scan();
        scan.status = ScanStatus::Failed;
        scan.meta = meta;
        let p = dir.join(format!("m{k}.npz"));
        save_scan(&p, &scan).unwrap();
        assert_same_scan(&scan, &load_scan(&p).unwrap());
    }
}

#[test]
fn npz_save_replaces_whole_file_and_refuses_bad_places() {
    let dir = test_dir("npz-replace");
    let p = dir.join("s.npz");
    let mut scan = aborted_scan();
    save_scan(&p, &scan).unwrap();
    scan.status = ScanStatus::Complete;
    scan.sx.data.fill(1.5);
    save_scan(&p, &scan).unwrap();
    let back = load_scan(&p).unwrap();
    assert_eq!(back.sx.data[[4, 6]], 1.5);
    assert_eq!(back.status, ScanStatus::Complete);

    let e = save_scan(dir.join("no/such/dir/s.npz"), &scan)
        .unwrap_err()
        .to_string();
    assert!(e.contains("does not exist"), "{e}");
    // inconsistent channels are refused, not written
    let mut bad = aborted_scan();
    bad.sz.x[0] = 99.0;
    let e = save_scan(dir.join("bad.npz"), &bad)
        .unwrap_err()
        .to_string();
    assert!(e.contains("sz axes"), "{e}");
    assert!(!dir.join("bad.npz").exists());
    assert_eq!(files_in(&dir), vec!["s.npz"]);
}

#[test]
fn npz_load_errors_are_clear() {
    let dir = test_dir("npz-errors");
    let e = load_scan(dir.join("missing.npz")).unwrap_err();
    assert!(matches!(e, DataError::Io { .. }), "{e:?}");
    assert!(e.to_string().contains("missing.npz"));
    std::fs::write(dir.join("junk.npz"), b"this is not a zip file").unwrap();
    let e = load_scan(dir.join("junk.npz")).unwrap_err().to_string();
    assert!(e.contains("junk.npz") && e.contains("npz"), "{e}");
    std::fs::write(dir.join("empty.npz"), b"").unwrap();
    let e = load_scan(dir.join("empty.npz")).unwrap_err().to_string();
    assert!(e.contains("empty file"), "{e}");
}

#[test]
fn numpy_reads_scan_files() {
    let have_numpy = Command::new("python3")
        .args(["-c", "import numpy"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    // Never a silent skip: `.ci/run` installs numpy when it is missing.
    assert!(
        have_numpy,
        "numpy_reads_scan_files needs python3 with numpy: run `python3 -m pip install numpy` \
         (.ci/run does this when it is missing)"
    );
    let dir = test_dir("npz-numpy");
    let path = dir.join("scan.npz");
    let scan = aborted_scan();
    save_scan(&path, &scan).unwrap();
    let script = r#"
import json, sys
import numpy as np
f = np.load(sys.argv[1])
assert sorted(f.files) == ["meta", "sx", "sy", "sz", "x", "y"], f.files
for k in ("sx", "sy", "sz"):
    assert f[k].dtype == np.float64 and f[k].shape == (5, 7), (k, f[k].dtype, f[k].shape)
assert f["x"].shape == (7,) and f["y"].shape == (5,)
m = json.loads(f["meta"].tobytes())
assert m["status"] == "aborted", m
assert m["format"] == "bfpscope-scan" and m["format_version"] == 1
assert m["x_name"] == "x" and m["y_name"] == "z"
assert m["plan"]["kind"] == "scan_xz" and m["note"] == "µm ünïcode ✓"
sx, sz = f["sx"], f["sz"]
assert sx[0, 0] == 0.0 and np.signbit(sx[0, 0])
assert sx[0, 1] == 5e-324 and sx[0, 2] == np.finfo(np.float64).max
assert sz[0, 0] == 0.1 + 0.2
assert int(np.isnan(sx).sum()) == 10 and np.isnan(sx[4]).all() and not np.isnan(sx[3, :4]).any()
assert abs(f["x"][1] - (-0.3 + 0.1)) == 0.0 and f["y"][4] == 1.0 + 0.05 * 4
print("numpy ok", np.__version__, f["sx"].shape)
"#;
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(&path)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "numpy check failed:\n{stdout}\n{stderr}"
    );
    assert!(stdout.contains("numpy ok"), "{stdout}");
    eprintln!("{}", stdout.trim());
}

// ------------------------------------------------------------------ session store

fn tagged_scan(thread: usize, k: usize) -> Scan {
    let mut s = aborted_scan();
    s.meta = json!({"thread": thread, "k": k});
    s.sx.data[[1, 1]] = (thread * 1000 + k) as f64;
    s
}

#[test]
fn session_numbers_increase_and_skip_gaps() {
    let dir = test_dir("session-seq");
    let session = Session::open(&*dir).unwrap();
    let p1 = session.autosave(&tagged_scan(0, 1)).unwrap();
    let p2 = session.autosave(&tagged_scan(0, 2)).unwrap();
    assert_eq!(p1.file_name().unwrap(), "scan_0001.npz");
    assert_eq!(p2.file_name().unwrap(), "scan_0002.npz");
    // a gap and a file written by someone else: numbering continues after the highest
    std::fs::write(dir.join("scan_0007.npz"), b"someone else's bytes").unwrap();
    std::fs::write(dir.join("scan_0100.txt"), b"not a scan").unwrap();
    let p8 = session.autosave(&tagged_scan(0, 3)).unwrap();
    assert_eq!(p8.file_name().unwrap(), "scan_0008.npz");
    assert_eq!(
        std::fs::read(dir.join("scan_0007.npz")).unwrap(),
        b"someone else's bytes",
        "never overwritten"
    );
    assert_eq!(load_scan(&p1).unwrap().meta["k"], 1);
    assert_eq!(load_scan(&p8).unwrap().meta["k"], 3);
    assert_eq!(session.latest_scan_path().unwrap().unwrap(), p8);
    assert_eq!(
        files_in(&dir),
        vec![
            "scan_0001.npz",
            "scan_0002.npz",
            "scan_0007.npz",
            "scan_0008.npz",
            "scan_0100.txt"
        ],
        "no temporary files left"
    );
}

#[test]
fn session_concurrent_autosaves_get_distinct_files() {
    let dir = test_dir("session-threads");
    let session = Session::open(&*dir).unwrap();
    let (threads, per) = (6, 5);
    let handles: Vec<_> = (0..threads)
        .map(|t| {
            let s = session.clone();
            std::thread::spawn(move || {
                (0..per)
                    .map(|k| s.autosave(&tagged_scan(t, k)).unwrap())
                    .collect::<Vec<_>>()
            })
        })
        .collect();
    let mut paths: Vec<PathBuf> = handles
        .into_iter()
        .flat_map(|h| h.join().unwrap())
        .collect();
    paths.sort();
    paths.dedup();
    assert_eq!(paths.len(), threads * per, "every save got its own file");
    let expected: Vec<String> = (1..=threads * per)
        .map(|n| format!("scan_{n:04}.npz"))
        .collect();
    assert_eq!(files_in(&dir), expected);
    // each file holds exactly the scan that was saved under its name
    let mut seen = std::collections::BTreeSet::new();
    for p in &paths {
        let s = load_scan(p).unwrap();
        let (t, k) = (
            s.meta["thread"].as_u64().unwrap() as usize,
            s.meta["k"].as_u64().unwrap() as usize,
        );
        assert_eq!(s.sx.data[[1, 1]], (t * 1000 + k) as f64);
        assert!(seen.insert((t, k)));
    }
    assert_eq!(seen.len(), threads * per);
}

#[test]
fn session_reserved_paths_are_never_handed_out_twice() {
    let dir = test_dir("session-reserve");
    let session = Session::open(&*dir).unwrap();
    let a = session.next_scan_path().unwrap();
    let b = session.next_scan_path().unwrap();
    assert_eq!(a.file_name().unwrap(), "scan_0001.npz");
    assert_eq!(b.file_name().unwrap(), "scan_0002.npz");
    // an unwritten reservation reads back as a clear error
    let e = load_scan(&a).unwrap_err().to_string();
    assert!(e.contains("reserved"), "{e}");
    save_scan(&a, &tagged_scan(1, 1)).unwrap();
    assert_eq!(load_scan(&a).unwrap().meta["thread"], 1);
    // autosave does not reuse the reserved-but-empty slot 2
    let c = session.autosave(&tagged_scan(1, 2)).unwrap();
    assert_eq!(c.file_name().unwrap(), "scan_0003.npz");
}

#[test]
fn session_folders() {
    let t = std::time::UNIX_EPOCH + std::time::Duration::from_secs(1_795_219_200);
    assert_eq!(
        Session::default_dir(Path::new("bfpscope_data"), t),
        Path::new("bfpscope_data/2026-11-21")
    );
    let dir = test_dir("session-open");
    let nested = dir.join("a/b");
    let s = Session::open(&nested).unwrap();
    assert!(nested.is_dir());
    assert_eq!(s.dir(), nested);
    std::fs::write(dir.join("file"), b"x").unwrap();
    let e = Session::open(dir.join("file")).unwrap_err().to_string();
    assert!(e.contains("not a folder"), "{e}");
    let s = Session::open_or_default(Some(&*dir)).unwrap();
    assert_eq!(s.dir(), &*dir);
}

// ------------------------------------------------------------------ TIFF

#[test]
fn tiff_round_trip_float32() {
    let dir = test_dir("tiff");
    let mut img = aborted_scan().sy;
    img.data[[0, 0]] = 1.0 / 3.0; // not representable in f32
    let p = dir.join("sy.tif");
    save_tiff(&p, &img).unwrap();
    let back = load_tiff(&p).unwrap();
    assert_eq!(back.shape(), img.shape());
    for (a, b) in img.data.iter().zip(back.data.iter()) {
        if a.is_nan() {
            assert!(b.is_nan());
        } else {
            assert_eq!(*b, f64::from(*a as f32), "values equal as f32");
        }
    }
    assert_eq!(back.data[[0, 0]], f64::from(1.0f32 / 3.0));
    for (a, b) in img.x.iter().zip(&back.x).chain(img.y.iter().zip(&back.y)) {
        assert!((a - b).abs() < 1e-12, "axes: {a} vs {b}");
    }
    assert_eq!((back.x_name.as_str(), back.y_name.as_str()), ("x", "z"));
    assert_eq!(files_in(&dir), vec!["sy.tif"]);
}

#[test]
fn tiff_header_is_what_imagej_expects() {
    use tiff::decoder::{ifd::Value, Decoder};
    use tiff::tags::Tag;
    let dir = test_dir("tiff-header");
    let img = Image::new(
        Array2::from_shape_fn((4, 6), |(i, j)| i as f64 - j as f64 * 0.5),
        (0..6).map(|j| 2.0 + 0.025 * j as f64).collect(),
        (0..4).map(|i| -1.0 + 0.025 * i as f64).collect(),
    );
    let p = dir.join("img.tiff");
    save_tiff(&p, &img).unwrap();
    let mut d = Decoder::new(std::io::BufReader::new(std::fs::File::open(&p).unwrap())).unwrap();
    assert_eq!(d.dimensions().unwrap(), (6, 4));
    assert_eq!(d.get_tag_u32(Tag::BitsPerSample).unwrap(), 32);
    assert_eq!(
        d.get_tag_u32(Tag::SampleFormat).unwrap(),
        3,
        "IEEE floating point"
    );
    assert_eq!(d.get_tag_u32(Tag::SamplesPerPixel).unwrap(), 1);
    assert_eq!(
        d.get_tag_u32(Tag::PhotometricInterpretation).unwrap(),
        1,
        "BlackIsZero grayscale"
    );
    let desc = d
        .get_tag(Tag::ImageDescription)
        .unwrap()
        .into_string()
        .unwrap();
    assert!(desc.starts_with("ImageJ="), "{desc}");
    assert!(desc.contains("\nunit=micron\n"), "{desc}");
    assert!(desc.contains("\nmin=-2.5\nmax=3\n"), "{desc}");
    let prop = |k: &str| -> f64 {
        let line = desc
            .lines()
            .find(|l| l.starts_with(&format!("{k}=")))
            .unwrap_or_else(|| panic!("{k} in {desc}"));
        line[k.len() + 1..].parse().unwrap()
    };
    assert!((prop("xorigin") + 80.0).abs() < 1e-9, "{desc}");
    assert!((prop("yorigin") - 40.0).abs() < 1e-9, "{desc}");
    match d.get_tag(Tag::XResolution).unwrap() {
        Value::Rational(n, den) => assert!(
            (f64::from(n) / f64::from(den) - 40.0).abs() < 1e-9,
            "40 px/µm"
        ),
        v => panic!("XResolution is {v:?}"),
    }
    // not a TIFF
    std::fs::write(dir.join("x.tif"), b"nope").unwrap();
    let e = load_tiff(dir.join("x.tif")).unwrap_err().to_string();
    assert!(e.contains("x.tif") && e.contains("TIFF"), "{e}");
}

// ------------------------------------------------------------------ CSV

#[test]
fn csv_profile_round_trip() {
    let dir = test_dir("csv-profile");
    let p = Profile::new(
        vec![-0.5, -0.25, 0.0, 0.25, 1e-300],
        vec![0.1 + 0.2, f64::NAN, -0.0, 1.0 / 3.0, f64::NEG_INFINITY],
    )
    .with_t_name("arc length");
    let path = dir.join("profile.csv");
    save_csv_profile(&path, &p).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines[0], "arc length_um,value");
    assert_eq!(lines[1], "-0.5,0.30000000000000004");
    assert_eq!(lines[2], "-0.25,nan");
    assert_eq!(lines[3], "0,-0");
    assert_eq!(lines[5], "1e-300,-inf");
    let back = load_csv_profile(&path).unwrap();
    assert_eq!(back.t_name, "arc length");
    assert_eq!(bits(&back.t), bits(&p.t));
    assert_eq!(bits(&back.v), bits(&p.v));
}

#[test]
fn csv_table_round_trip_and_errors() {
    let dir = test_dir("csv-table");
    let path = dir.join("table.csv");
    let headers = ["d_nm", "mass, MDa", "say \"hi\""];
    let cols = vec![
        vec![10.0, 20.0, 40.0],
        vec![1.5e-7, 2.0e9, f64::NAN],
        vec![1.0, 2.0, 3.0],
    ];
    save_csv_table(&path, &headers, &cols).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(
        text.starts_with("d_nm,\"mass, MDa\",\"say \"\"hi\"\"\"\n"),
        "{text}"
    );
    assert!(text.contains("\n40,nan,3\n"), "{text}");
    let (h, c) = load_csv_table(&path).unwrap();
    assert_eq!(h, headers);
    for (a, b) in cols.iter().zip(&c) {
        assert_eq!(bits(a), bits(b));
    }
    let e = save_csv_table(&path, &["a", "b"], &[vec![1.0, 2.0], vec![1.0]])
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("column 1") && e.contains("1 rows") && e.contains("(2 rows)"),
        "{e}"
    );
    let e = save_csv_table(&path, &["a"], &[vec![1.0], vec![2.0]])
        .unwrap_err()
        .to_string();
    assert!(e.contains("headers"), "{e}");
    // the failed saves left the good file alone
    assert_eq!(load_csv_table(&path).unwrap().0, headers);
    std::fs::write(dir.join("bad.csv"), "a,b\n1,2\n3,x\n").unwrap();
    let e = load_csv_table(dir.join("bad.csv")).unwrap_err().to_string();
    assert!(e.contains("line 3") && e.contains("\"x\""), "{e}");
}
