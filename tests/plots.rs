//! Every figure type is rendered to PNG, decoded, and checked for content: many colours, text
//! pixels where the title is, the colour bar, the expected colours of the heat map, grey NaN
//! pixels. Set `BFPSCOPE_PLOT_OUT=/some/dir` to keep the figures for looking at them.

use crate::support::cleanup;

use bfpscope::analysis::stats::histogram;
use bfpscope::data::{DataError, Image, Profile, Scan, ScanStatus};
use bfpscope::plot::{
    image_plot_area, plot_hist, plot_image, plot_profile, plot_scan, plot_xy, Colormap, PlotOpts,
    ScanPlotOpts, Series, SeriesStyle, XyOpts,
};
use ndarray::Array2;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// Where a test writes its figures: `$BFPSCOPE_PLOT_OUT` (kept), else a temporary folder that
/// is removed when the test passes.
struct OutDir {
    dir: PathBuf,
    keep: bool,
}

impl std::ops::Deref for OutDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.dir
    }
}

impl Drop for OutDir {
    fn drop(&mut self) {
        if !self.keep && !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

fn out_dir(name: &str) -> OutDir {
    let (dir, keep) = match std::env::var_os("BFPSCOPE_PLOT_OUT") {
        Some(d) => (PathBuf::from(d), true),
        None => (
            cleanup::at_exit(
                &std::env::temp_dir().join(format!("bfpscope-plots-{}-{name}", std::process::id())),
            ),
            false,
        ),
    };
    std::fs::create_dir_all(&dir).unwrap();
    OutDir { dir, keep }
}

struct Png {
    w: usize,
    h: usize,
    px: Vec<(u8, u8, u8)>,
}

impl Png {
    fn read(path: &Path) -> Png {
        let bytes = std::fs::read(path).unwrap();
        assert_eq!(
            &bytes[..8],
            b"\x89PNG\r\n\x1a\n",
            "{} is a PNG",
            path.display()
        );
        let dec = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut reader = dec.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        let ch = match info.color_type {
            png::ColorType::Rgb => 3,
            png::ColorType::Rgba => 4,
            c => panic!("unexpected colour type {c:?}"),
        };
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
        let px = buf[..info.buffer_size()]
            .chunks(ch)
            .map(|c| (c[0], c[1], c[2]))
            .collect();
        Png {
            w: info.width as usize,
            h: info.height as usize,
            px,
        }
    }
    fn at(&self, x: usize, y: usize) -> (u8, u8, u8) {
        self.px[y * self.w + x]
    }
    fn distinct(&self) -> usize {
        self.px.iter().collect::<HashSet<_>>().len()
    }
    /// Pixels of colour `c` whose whole 3x3 neighbourhood has that colour (areas, not text).
    fn solid(&self, c: (u8, u8, u8)) -> usize {
        let mut n = 0;
        for y in 1..self.h - 1 {
            for x in 1..self.w - 1 {
                if (0..3).all(|dy| (0..3).all(|dx| self.at(x + dx - 1, y + dy - 1) == c)) {
                    n += 1;
                }
            }
        }
        n
    }
    fn count(&self, f: impl Fn((u8, u8, u8)) -> bool) -> usize {
        self.px.iter().filter(|&&p| f(p)).count()
    }
    /// Dark (text or axis) pixels in rows `y0..y1`.
    fn dark_in_rows(&self, y0: usize, y1: usize) -> usize {
        (y0..y1.min(self.h))
            .flat_map(|y| (0..self.w).map(move |x| (x, y)))
            .filter(|&(x, y)| is_dark(self.at(x, y)))
            .count()
    }
}

/// Number of separate runs of rows holding dark pixels in columns `x0..x1` (one per label).
fn text_runs(png: &Png, x0: usize, x1: usize) -> usize {
    let rows: Vec<bool> = (0..png.h)
        .map(|y| (x0..x1).any(|x| is_dark(png.at(x, y))))
        .collect();
    rows.windows(2).filter(|w| !w[0] && w[1]).count() + usize::from(rows.first() == Some(&true))
}

fn is_dark((r, g, b): (u8, u8, u8)) -> bool {
    r < 90 && g < 90 && b < 90
}

fn close(a: (u8, u8, u8), b: (u8, u8, u8), tol: i32) -> bool {
    (i32::from(a.0) - i32::from(b.0)).abs() <= tol
        && (i32::from(a.1) - i32::from(b.1)).abs() <= tol
        && (i32::from(a.2) - i32::from(b.2)).abs() <= tol
}

/// Synthetic dipole-like Sx image `x·exp(-(x²+y²)/0.16)` on a square grid.
fn dipole(n: usize, half: f64) -> Image {
    let ax: Vec<f64> = (0..n)
        .map(|k| -half + 2.0 * half * k as f64 / (n - 1) as f64)
        .collect();
    let data = Array2::from_shape_fn((n, n), |(i, j)| {
        let (x, y) = (ax[j], ax[i]);
        x * (-(x * x + y * y) / 0.16).exp()
    });
    Image::new(data, ax.clone(), ax)
}

fn scan_xy(n: usize) -> Scan {
    let sx = dipole(n, 1.0);
    let mut sy = sx.clone();
    sy.data = Array2::from_shape_fn((n, n), |(i, j)| 0.7 * sx.data[[j, i]]);
    let mut sz = sx.clone();
    sz.data = sx.data.mapv(|v| v.abs()) + 1.0;
    Scan {
        sx,
        sy,
        sz,
        status: ScanStatus::Complete,
        meta: serde_json::json!({}),
        raw: Vec::new(),
        flags: Default::default(),
    }
}

/// Deterministic pseudo-random normal numbers (LCG + Box–Muller).
fn normals(n: usize, mut seed: u64) -> Vec<f64> {
    let mut u = move || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((seed >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    (0..n)
        .map(|_| (-2.0 * u().ln()).sqrt() * (2.0 * std::f64::consts::PI * u()).cos())
        .collect()
}

const RDBU_BLUE_END: (u8, u8, u8) = (0x05, 0x30, 0x61);
const RDBU_RED_END: (u8, u8, u8) = (0x67, 0x00, 0x1f);

#[test]
fn heat_map_of_dipole_has_colours_text_and_colour_bar() {
    let dir = out_dir("heat");
    let img = dipole(64, 1.0);
    let path = dir.join("image_sx.png");
    plot_image(
        &path,
        &img,
        &PlotOpts::diverging("Sx").with_title("Sx of a dipole x·exp(-(x²+y²)/0.16)"),
    )
    .unwrap();
    let png = Png::read(&path);
    assert!(png.w > 500 && png.h > 450, "{}x{}", png.w, png.h);
    assert!(png.distinct() > 200, "only {} colours", png.distinct());
    assert!(png.dark_in_rows(0, 40) > 100, "title text is drawn");
    let reds = png.count(|(r, g, b)| r > 150 && g < 120 && b < 120);
    let blues = png.count(|(r, _, b)| b > 150 && r < 120);
    assert!(reds > 1000 && blues > 1000, "reds {reds}, blues {blues}");
    // symmetric map and antisymmetric image: the darkest red and darkest blue pixels of the
    // heat map are mirror images (same distance from white at the two ends of the map)
    let deep_red = png.count(|p| close(p, (0x8a, 0x0b, 0x25), 25));
    let deep_blue = png.count(|p| close(p, (0x12, 0x4a, 0x86), 25));
    assert!(
        deep_red > 100 && deep_blue > 100,
        "deep red {deep_red}, deep blue {deep_blue}"
    );
    assert!(
        (deep_red as f64 / deep_blue as f64 - 1.0).abs() < 0.25,
        "deep red {deep_red}, deep blue {deep_blue}"
    );
    // the colour bar: one pixel column holding both ends of the diverging map
    let bar_column = (0..png.w).any(|x| {
        let col: Vec<_> = (0..png.h).map(|y| png.at(x, y)).collect();
        col.iter().any(|&p| close(p, RDBU_BLUE_END, 12))
            && col.iter().any(|&p| close(p, RDBU_RED_END, 12))
    });
    assert!(bar_column, "colour bar with both ends of the map");
    assert_eq!(
        png.solid((150, 150, 150)),
        0,
        "no NaN grey area without NaN pixels"
    );
}

#[test]
fn nan_pixels_are_grey_and_sequential_map_is_used() {
    let dir = out_dir("nan");
    let mut img = dipole(48, 1.0);
    img.data.mapv_inplace(|v| v.abs());
    for i in 36..48 {
        for j in 0..48 {
            img.data[[i, j]] = f64::NAN;
        }
    }
    let path = dir.join("image_sz_nan.png");
    let opts = PlotOpts {
        title: "|Sx| with an aborted tail".into(),
        label: "|Sx|".into(),
        ..PlotOpts::default()
    };
    assert_eq!(opts.colormap, Colormap::Sequential);
    plot_image(&path, &img, &opts).unwrap();
    let png = Png::read(&path);
    let grey = png.solid((150, 150, 150));
    assert!(grey > 3000, "NaN rows drawn grey: {grey} px");
    let viridis_dark = png.count(|p| close(p, (0x44, 0x01, 0x54), 10));
    let viridis_yellow = png.count(|p| close(p, (0xfd, 0xe7, 0x25), 10));
    assert!(
        viridis_dark > 500 && viridis_yellow > 20,
        "dark {viridis_dark}, yellow {viridis_yellow}"
    );
}

#[test]
fn pixels_are_square_in_micrometres() {
    // 64 columns x 32 rows at equal spacing: twice as wide as high
    let img = Image::new(
        Array2::zeros((32, 64)),
        (0..64).map(|j| j as f64 * 0.05).collect(),
        (0..32).map(|i| i as f64 * 0.05).collect(),
    );
    let (w, h) = image_plot_area(&img, 480);
    assert_eq!((w, h), (480, 240));
    // equal pixel counts but y spacing twice x spacing: twice as high as wide
    let img = Image::new(
        Array2::zeros((40, 40)),
        (0..40).map(|j| j as f64 * 0.01).collect(),
        (0..40).map(|i| i as f64 * 0.02).collect(),
    );
    let (w, h) = image_plot_area(&img, 480);
    assert_eq!((w, h), (240, 480));
    // the drawn figure follows the layout: an XZ scan 2 µm wide and 4 µm deep
    let dir = out_dir("aspect");
    let xz = Image::new(
        Array2::from_shape_fn((40, 20), |(i, j)| {
            ((i as f64 - 20.0) * 0.1).exp() * (j as f64 - 9.5)
        }),
        (0..20).map(|j| -1.0 + 0.1 * j as f64).collect(),
        (0..40).map(|i| 0.1 * i as f64).collect(),
    )
    .with_axis_names("x", "z");
    let path = dir.join("image_xz.png");
    plot_image(&path, &xz, &PlotOpts::diverging("Sx").with_title("XZ scan")).unwrap();
    let png = Png::read(&path);
    let (w, h) = image_plot_area(&xz, 480);
    assert_eq!((w, h), (240, 480));
    assert!(png.h > png.w / 2, "tall figure: {}x{}", png.w, png.h);
}

#[test]
fn scan_figure_has_three_panels() {
    let dir = out_dir("scan");
    let mut scan = scan_xy(64);
    for i in 50..64 {
        for j in 0..64 {
            if i > 50 || j > 20 {
                scan.sx.data[[i, j]] = f64::NAN;
                scan.sy.data[[i, j]] = f64::NAN;
                scan.sz.data[[i, j]] = f64::NAN;
            }
        }
    }
    scan.status = ScanStatus::Aborted;
    let path = dir.join("scan.png");
    plot_scan(
        &path,
        &scan,
        &ScanPlotOpts {
            title: "bead scan".into(),
            ..ScanPlotOpts::default()
        },
    )
    .unwrap();
    let png = Png::read(&path);
    assert!(
        png.w > 3 * 400,
        "three panels side by side: width {}",
        png.w
    );
    assert!(png.dark_in_rows(0, 40) > 100, "title drawn");
    assert!(png.solid((150, 150, 150)) > 2000, "unmeasured pixels grey");
    let viridis = png.count(|p| close(p, (0x44, 0x01, 0x54), 12));
    assert!(viridis > 200, "Sz panel uses the sequential map");
    let path2 = dir.join("scan_xy_shared.png");
    let opts = ScanPlotOpts {
        title: "shared Sx/Sy scale".into(),
        include_sz: false,
        shared_xy_scale: true,
    };
    plot_scan(&path2, &scan_xy(48), &opts).unwrap();
    let png2 = Png::read(&path2);
    assert!(png2.w < png.w, "two panels are narrower than three");
}

#[test]
fn profiles_with_legend() {
    let dir = out_dir("profile");
    let img = dipole(81, 1.0);
    let sx_row = img.row(40).unwrap();
    let mut sy_col = img.col(60).unwrap();
    sy_col.v[10] = f64::NAN; // a gap in the line
    let path = dir.join("profile.png");
    plot_profile(
        &path,
        &[("Sx, row 40", &sx_row), ("Sx, column 60", &sy_col)],
        &XyOpts::new("Line profiles", "", "Sx"),
    )
    .unwrap();
    let png = Png::read(&path);
    assert!(png.distinct() > 30, "{}", png.distinct());
    assert!(png.dark_in_rows(0, 40) > 100, "title drawn");
    let blue = png.count(|p| close(p, (0x1f, 0x77, 0xb4), 20));
    let orange = png.count(|p| close(p, (0xff, 0x7f, 0x0e), 20));
    assert!(
        blue > 300 && orange > 300,
        "two curves: blue {blue}, orange {orange}"
    );
}

#[test]
fn histogram_bins() {
    let h = histogram(&[0.0, 0.1, 0.5, 0.99, 1.0, f64::NAN, 0.25], 4, None).unwrap();
    assert_eq!(h.edges, vec![0.0, 0.25, 0.5, 0.75, 1.0]);
    assert_eq!(
        h.counts,
        vec![2, 1, 1, 2],
        "0.25 opens bin 1, 1.0 closes the last bin"
    );
    assert_eq!((h.n_skipped, h.count()), (1, 6));
    let h = histogram(&[3.0; 4], 10, None).unwrap();
    assert!(h.all_equal);
    assert_eq!(
        (h.counts.clone(), h.edges.clone()),
        (vec![4], vec![2.85, 3.15])
    );
    let e = histogram(&[1.0, f64::NEG_INFINITY], 3, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("values[1] = -inf"), "{e}");
}

#[test]
fn histogram_counts_and_note() {
    let dir = out_dir("hist");
    let mut v = normals(2000, 7);
    v[3] = f64::NAN;
    let path = dir.join("hist.png");
    plot_hist(&path, &v, 40, &XyOpts::new("Bead masses", "mass (MDa)", "")).unwrap();
    let png = Png::read(&path);
    let bars = png.count(|(r, g, b)| b > 150 && r < 130 && g > 100 && g < 200);
    assert!(bars > 20_000, "filled bars: {bars} px");
    assert!(png.dark_in_rows(0, 40) > 100, "title drawn");
}

#[test]
fn log_log_scaling_with_error_bars_and_pareto() {
    let dir = out_dir("xy");
    let d: Vec<f64> = vec![20.0, 30.0, 50.0, 80.0, 100.0, 150.0, 200.0];
    let s: Vec<f64> = d.iter().map(|d| 1e-6 * d * d * d).collect();
    let err: Vec<f64> = s.iter().map(|s| 0.15 * s).collect();
    let fit_d: Vec<f64> = (0..50)
        .map(|k| 15.0 * (250.0f64 / 15.0).powf(k as f64 / 49.0))
        .collect();
    let fit_s: Vec<f64> = fit_d.iter().map(|d| 1e-6 * d * d * d).collect();
    let series = [
        Series::points("measured", d, s).with_yerr(err),
        Series::line("∝ d³", fit_d, fit_s),
    ];
    let path = dir.join("scaling_loglog.png");
    plot_xy(
        &path,
        &series,
        &XyOpts::new("Signal vs diameter", "d (nm)", "signal (V)").log_log(),
    )
    .unwrap();
    let png = Png::read(&path);
    assert!(png.distinct() > 30);
    assert!(png.dark_in_rows(0, 40) > 100, "title drawn");

    // error vs time for two knobs
    let t1 = vec![0.01, 0.03, 0.1, 0.3, 1.0, 3.0];
    let e1 = vec![3e-2, 8e-3, 2e-3, 6e-4, 2e-4, 1.5e-4];
    let t2 = vec![0.02, 0.2, 2.0, 20.0];
    let e2 = vec![1e-1, 1e-2, 1e-3, 1e-4];
    let series = [
        Series::line("quadrature order", t1, e1).with_style(SeriesStyle::LinePoints),
        Series::line("template spacing", t2, e2).with_style(SeriesStyle::LinePoints),
    ];
    let path = dir.join("pareto.png");
    plot_xy(
        &path,
        &series,
        &XyOpts::new("Accuracy vs time", "time (s)", "relative error").log_log(),
    )
    .unwrap();
    let png = Png::read(&path);
    assert!(
        png.count(|p| close(p, (0xff, 0x7f, 0x0e), 20)) > 200,
        "second series drawn"
    );

    // less than a decade on a log axis still has tick labels (plotters' own log axis has none)
    let path = dir.join("log_narrow.png");
    let x: Vec<f64> = (0..20).map(|k| k as f64).collect();
    let y: Vec<f64> = x.iter().map(|x| 2.5 + 5.0 * x / 19.0).collect();
    let o = XyOpts {
        log_y: true,
        ..XyOpts::new("narrow log range", "k", "value")
    };
    plot_xy(&path, &[Series::line("", x, y)], &o).unwrap();
    let png = Png::read(&path);
    // tick labels sit between the rotated axis description and the axis: count separate labels
    let labels = text_runs(&png, 36, 88);
    assert!(labels >= 4, "y tick labels drawn: {labels}");
}

#[test]
fn svg_output_when_asked() {
    let dir = out_dir("svg");
    let path = dir.join("image_sx.svg");
    plot_image(
        &path,
        &dipole(16, 1.0),
        &PlotOpts::diverging("Sx").with_title("SVG"),
    )
    .unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.starts_with("<svg"), "{}", &text[..40.min(text.len())]);
    assert!(
        text.contains("x (µm)") && text.contains("<text"),
        "axis labels as text"
    );
    assert!(
        text.matches("<rect").count() >= 16 * 16,
        "one rectangle per pixel"
    );
}

#[test]
fn bad_input_gives_clear_errors_and_no_files() {
    // always a fresh private folder: the test checks that nothing was written into it
    let dir = OutDir {
        dir: cleanup::at_exit(
            &std::env::temp_dir().join(format!("bfpscope-plots-{}-errors", std::process::id())),
        ),
        keep: false,
    };
    let _ = std::fs::remove_dir_all(&*dir);
    std::fs::create_dir_all(&*dir).unwrap();
    let nan = Image::new(
        Array2::from_elem((4, 4), f64::NAN),
        vec![0.0, 1.0, 2.0, 3.0],
        vec![0.0, 1.0, 2.0, 3.0],
    );
    let msg = |r: Result<(), DataError>| r.unwrap_err().to_string();

    let e = msg(plot_image(
        dir.join("a.png"),
        &nan,
        &PlotOpts::diverging("Sx"),
    ));
    assert!(e.contains("all 16 pixels are NaN"), "{e}");
    let e = msg(plot_image(
        dir.join("a.jpg"),
        &dipole(8, 1.0),
        &PlotOpts::default(),
    ));
    assert!(e.contains(".png or .svg"), "{e}");
    let e = msg(plot_image(
        dir.join("nope/a.png"),
        &dipole(8, 1.0),
        &PlotOpts::default(),
    ));
    assert!(e.contains("does not exist"), "{e}");
    let bad_range = PlotOpts {
        range: Some((1.0, -1.0)),
        ..PlotOpts::default()
    };
    let e = msg(plot_image(dir.join("a.png"), &dipole(8, 1.0), &bad_range));
    assert!(e.contains("vmin < vmax"), "{e}");

    let e = msg(plot_xy(dir.join("b.png"), &[], &XyOpts::default()));
    assert!(e.contains("no series"), "{e}");
    let e = msg(plot_xy(
        dir.join("b.png"),
        &[Series::line("a", vec![1.0, 2.0], vec![1.0])],
        &XyOpts::default(),
    ));
    assert!(
        e.contains("\"a\"") && e.contains("x has 2 values but y has 1"),
        "{e}"
    );
    let e = msg(plot_xy(
        dir.join("b.png"),
        &[Series::line("err", vec![1.0, 2.0], vec![1.0, 0.0])],
        &XyOpts::default().log_log(),
    ));
    assert!(e.contains("y[1] = 0") && e.contains("log y axis"), "{e}");
    let e = msg(plot_xy(
        dir.join("b.png"),
        &[Series::line("n", vec![f64::NAN], vec![1.0])],
        &XyOpts::default(),
    ));
    assert!(e.contains("no finite points"), "{e}");
    let e = msg(plot_xy(
        dir.join("b.png"),
        &[Series::line("i", vec![1.0], vec![f64::INFINITY])],
        &XyOpts::default(),
    ));
    assert!(e.contains("y[0] = inf"), "{e}");

    let e = msg(plot_hist(
        dir.join("c.png"),
        &[1.0, 2.0],
        0,
        &XyOpts::default(),
    ));
    assert!(
        e.contains("bins = 0") && e.contains("1 ≤ bins ≤ 10000"),
        "{e}"
    );
    let e = msg(plot_hist(
        dir.join("c.png"),
        &[f64::NAN, f64::NAN],
        10,
        &XyOpts::default(),
    ));
    assert!(e.contains("all 2 values are NaN"), "{e}");
    let e = msg(plot_hist(dir.join("c.png"), &[], 10, &XyOpts::default()));
    assert!(e.contains("empty"), "{e}");
    let e = msg(plot_profile(dir.join("d.png"), &[], &XyOpts::default()));
    assert!(e.contains("no profiles"), "{e}");

    let left: Vec<_> = std::fs::read_dir(&*dir).unwrap().collect();
    assert!(left.is_empty(), "nothing written on error: {left:?}");
}

#[test]
fn degenerate_but_valid_inputs_still_plot() {
    let dir = out_dir("degenerate");
    // constant image, single row, single value histogram, single point
    let flat = Image::new(
        Array2::from_elem((3, 3), 2.0),
        vec![0.0, 1.0, 2.0],
        vec![0.0, 1.0, 2.0],
    );
    plot_image(dir.join("flat.png"), &flat, &PlotOpts::default()).unwrap();
    let line = Image::new(
        Array2::from_shape_fn((1, 30), |(_, j)| j as f64),
        (0..30).map(|j| j as f64 * 0.1).collect(),
        vec![0.5],
    );
    plot_image(dir.join("one_row.png"), &line, &PlotOpts::default()).unwrap();
    assert!(Png::read(&dir.join("one_row.png")).distinct() > 30);
    plot_hist(dir.join("hist_one.png"), &[3.0; 5], 10, &XyOpts::default()).unwrap();
    plot_xy(
        dir.join("xy_one.png"),
        &[Series::points("p", vec![1.0], vec![1.0])],
        &XyOpts::default().log_log(),
    )
    .unwrap();
    let p = Profile::new(vec![0.0, 1.0], vec![1.0, 1.0]);
    plot_profile(
        dir.join("profile_flat.png"),
        &[("flat", &p)],
        &XyOpts::default(),
    )
    .unwrap();
    for f in ["flat.png", "hist_one.png", "xy_one.png", "profile_flat.png"] {
        assert!(Png::read(&dir.join(f)).distinct() > 10, "{f}");
    }
}

/// A raster from a 2-input digitiser has no Sz (all NaN); its plot shows Sx and Sy
/// and says Sz was left out (it failed with "Sz has no data"). No data at all is still an error.
#[test]
fn a_scan_without_sz_plots_the_channels_with_data() {
    let dir = out_dir("nosz");
    let mut scan = scan_xy(48);
    scan.sz.data.fill(f64::NAN);
    assert_eq!(bfpscope::plot::empty_channels(&scan, true), vec!["Sz"]);
    let path = dir.join("no_sz.png");
    plot_scan(&path, &scan, &ScanPlotOpts::default()).unwrap();
    let png = Png::read(&path);
    let two = dir.join("two.png");
    plot_scan(
        &two,
        &scan_xy(48),
        &ScanPlotOpts {
            include_sz: false,
            ..ScanPlotOpts::default()
        },
    )
    .unwrap();
    assert_eq!(
        png.w,
        Png::read(&two).w,
        "two panels, as with include_sz off"
    );
    assert!(
        png.dark_in_rows(0, 40) > 100,
        "the title says what was left out"
    );
    let viridis = png.count(|p| close(p, (0x44, 0x01, 0x54), 12));
    assert!(viridis < 20, "no Sz panel: {viridis} viridis pixels");
    scan.sx.data.fill(f64::NAN);
    scan.sy.data.fill(f64::NAN);
    let e = plot_scan(dir.join("none.png"), &scan, &ScanPlotOpts::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("the scan has no data: all 2304 pixels of Sx, Sy, Sz are NaN"),
        "{e}"
    );
}
