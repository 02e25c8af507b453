//! Figures and interchange files: `plot` (heat maps of scans and images), `plot_profile`,
//! `plot_hist`, `plot_xy`, `save_tiff` / `load_tiff` (float32 TIFF for Fiji), `save_csv`
//! (profiles and tables). Figures are PNG or SVG by extension, drawn with the embedded font.
//! Relative paths resolve in the session folder; parent folders are created; an existing file
//! is never replaced (a numbered name is used) unless `overwrite: true`; every save prints
//! where it went.

use super::ctx::Ctx;
use super::registry::{binding_list, fail, numbers, Doc, Opt, Opts, RResult, Registrar, Spec};
use super::types::{ImageRef, ProfileRef, ScanRef};
use crate::analysis::stats::MAX_BINS;
use crate::plot::{
    self as figure, plot_image, plot_scan, PlotOpts, ScanPlotOpts, Series, SeriesStyle, XyOpts,
};
use rhai::{Array, Dynamic, Map};
use std::path::Path;
use std::sync::Arc;

/// The options of this family's bindings, each key written once (`Opt`).
const BINS: Opt = Opt::new("bins", "int", "");
const CHANNEL: Opt = Opt::new("channel", "string", "");
const COLORMAP: Opt = Opt::new("colormap", "string", "");
const INCLUDE_SZ: Opt = Opt::new("include_sz", "bool", "");
const LABEL: Opt = Opt::new("label", "string", "");
const LOG_X: Opt = Opt::new("log_x", "bool", "");
const LOG_Y: Opt = Opt::new("log_y", "bool", "");
const OVERWRITE: Opt = Opt::new("overwrite", "bool", "");
const RANGE: Opt = Opt::new("range", "array", "");
const SHARED_XY_SCALE: Opt = Opt::new("shared_xy_scale", "bool", "");
const TITLE: Opt = Opt::new("title", "string", "");
const XLABEL: Opt = Opt::new("xlabel", "string", "");
const YLABEL: Opt = Opt::new("ylabel", "string", "");

/// The path to write (see [`super::console::output_path`]: relative paths in the session folder,
/// existing files never replaced unless `overwrite`).
fn prepare(c: &Ctx, who: &str, path: &str, overwrite: bool) -> RResult<String> {
    let p = super::console::output_path(c.store.dir(), who, path, overwrite)?;
    Ok(p.display().to_string())
}

/// Embed the script's provenance in the file just written (PNG text chunk, SVG comment, CSV
/// trailer; other formats untouched) and return its path.
fn stamp(c: &Ctx, path: &str) -> RResult<String> {
    let json = c.provenance().to_string();
    crate::data::provenance::embed(Path::new(path), &json)
        .map_err(|e| format!("provenance: {e}"))?;
    c.print(&format!("saved {path}"));
    let p = Path::new(path);
    if p.extension().is_some_and(|e| e == "png" || e == "svg") {
        let kept = keep_in_session(c, p)?;
        c.view_figure(&kept);
    }
    Ok(path.to_string())
}

/// Every figure is kept in the session folder: one written elsewhere (an absolute path) is
/// copied there too (numbered, never overwriting). Returns the copy in the session folder.
fn keep_in_session(c: &Ctx, p: &Path) -> RResult<std::path::PathBuf> {
    let session = c.store.dir();
    let inside = |q: &Path| {
        let (a, b) = (std::fs::canonicalize(q), std::fs::canonicalize(session));
        matches!((a, b), (Ok(a), Ok(b)) if a.starts_with(&b))
    };
    if inside(p) {
        return Ok(p.to_path_buf());
    }
    let name = p
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| "figure.png".into());
    let copy = super::console::output_path(session, "figure", &name, false)?;
    std::fs::copy(p, &copy).map_err(|e| {
        format!(
            "figure: cannot keep a copy in the session folder {}: {e}",
            copy.display()
        )
    })?;
    c.print(&format!(
        "  (a copy is kept in the session folder: {})",
        copy.display()
    ));
    Ok(copy)
}

fn ferr(who: &str, path: &str, e: impl std::fmt::Display) -> Box<rhai::EvalAltResult> {
    format!("{who}: {path}: {e}").into()
}

fn xy_opts(o: &Opts) -> RResult<XyOpts> {
    Ok(XyOpts {
        title: o.string(TITLE)?.unwrap_or_default(),
        xlabel: o.string(XLABEL)?.unwrap_or_default(),
        ylabel: o.string(YLABEL)?.unwrap_or_default(),
        log_x: o.bool_or(LOG_X, false)?,
        log_y: o.bool_or(LOG_Y, false)?,
    })
}

const XY_KEYS: &[(&str, &str, &str, &str)] = &[
    TITLE.doc("optional: figure title"),
    XLABEL.doc("optional: x-axis label"),
    YLABEL.doc("optional: y-axis label"),
    LOG_X.doc("optional: logarithmic x axis"),
    LOG_Y.doc("optional: logarithmic y axis"),
    OVERWRITE.doc(
        "optional: replace an existing file (default false: a numbered name, never overwriting)",
    ),
];

/// `plot_hist`'s number of bins when `bins` is not given.
const PLOT_HIST_BINS: i64 = 20;

const SCENE: &str = "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, d_nm: 110.0, n: 1.572}); let sc = simulate(s, #{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21}); let dir = status().data_dir;";

binding_list! {
    pub fn register {
        bind_plot, bind_line_plots, bind_plot_hist, bind_tiff, bind_save_csv
    }
}

/// `plot`: an image or a scan channel as a heat map.
fn bind_plot(r: &mut Registrar) {
    let d = Doc::func("plot")
        .arg("what", "Scan | Image", "", "a scan (Sx, Sy, Sz panels) or one image")
        .figure_file("figure file, .png or .svg (relative: in the session folder; an existing file is kept and a numbered name used unless overwrite: true)")
        .opts(&[
                TITLE.doc("optional: figure title"),
                OVERWRITE.doc("optional: replace an existing file (default false: a numbered name, never overwriting)"),
                CHANNEL.doc("optional (scans): plot only \"sx\", \"sy\" or \"sz\""),
                INCLUDE_SZ.doc("optional (scans): draw the Sz panel (default true)"),
                SHARED_XY_SCALE.doc("optional (scans): Sx and Sy on one colour range"),
                LABEL.doc("optional (images): colour-bar label"),
                COLORMAP.doc("optional (images): \"diverging\" (symmetric about 0) or \"sequential\" (default)"),
                RANGE.doc("optional (images): fixed colour range [lo, hi]"),
            ],
        )
        .summary("heat map with colour bar and µm axes: Sx/Sy diverging about 0, Sz sequential")
        .example(&format!("{SCENE} plot(sc, dir + \"/ex_scan.png\").ends_with(\"ex_scan.png\")"), "true")
        .example(&format!("{SCENE} plot(sc.sx, dir + \"/ex_sx.svg\", #{{colormap: \"diverging\", title: \"Sx\"}}).ends_with(\".svg\")"), "true")
        .example(&format!("{SCENE} plot(sc, dir + \"/ex.jpg\")"), "error: figure files end in .png or .svg")
        .example(&format!("{SCENE} plot(sc, dir + \"/ex.png\", #{{channel: \"sq\"}})"), "error: channel = \"sq\"");
    bind_figure(r, d, plot);
}

/// `plot_profile`, `plot_xy`: line figures.
fn bind_line_plots(r: &mut Registrar) {
    let d = Doc::func("plot_profile")
        .arg("profiles", "Profile | array | map", "", "one Profile, [Profile, …], or #{label: Profile, …}")
        .figure_file(FIGURE_FILE)
        .opts(XY_KEYS)
        .summary("line plot of one or more profiles with a legend")
        .example(&format!("{SCENE} plot_profile(#{{sx: sc.sx.row(10), sy: sc.sy.col(10)}}, dir + \"/ex_prof.png\", #{{ylabel: \"signal\"}}).ends_with(\".png\")"), "true")
        .example(&format!("{SCENE} plot_profile([], dir + \"/ex_prof.png\")"), "error: no profiles");
    bind_figure(r, d, plot_profile);

    let d = Doc::func("plot_xy")
        .arg("series", "array", "", "[#{x: [..], y: [..], label, style: \"line\" | \"points\" | \"linepoints\", yerr: [..]}, …]")
        .figure_file(FIGURE_FILE)
        .opts(XY_KEYS)
        .summary("x–y plot of curves and points with error bars, optionally log–log")
        .example("let p = status().data_dir + \"/ex_xy.png\"; plot_xy([#{x: [50.0, 100.0, 200.0], y: [1.0, 8.0, 64.0], label: \"d³\", style: \"linepoints\"}], p, #{log_x: true, log_y: true}) == p", "true")
        .example("plot_xy([#{x: [1.0, 2.0], y: [1.0]}], status().data_dir + \"/ex_xy.png\")", "error: x and y");
    bind_figure(r, d, plot_xy);
}

/// `plot_hist`: a histogram figure.
fn bind_plot_hist(r: &mut Registrar) {
    let d = Doc::func("plot_hist")
        .arg("values", "array", "", "numbers (NaN skipped and noted)")
        .figure_file(FIGURE_FILE)
        .opts(&[
                BINS.doc(format!("optional: number of bins (default {PLOT_HIST_BINS})").as_str()),
                TITLE.doc("optional: figure title"),
                OVERWRITE.doc("optional: replace an existing file (default false: a numbered name, never overwriting)"),
                XLABEL.doc("optional: x-axis label"),
                YLABEL.doc("optional: y-axis label (default \"count\")"),
            ],
        )
        .summary("histogram figure (e.g. bead diameters, Fig. 3b)")
        .example("let p = status().data_dir + \"/ex_hist.png\"; plot_hist([1.0, 2.0, 2.0, 3.0], p, #{bins: 3, xlabel: \"d (nm)\"}) == p", "true")
        .example("plot_hist([1.0], status().data_dir + \"/ex_hist.png\", #{bins: 0})", "error: bins");
    bind_figure(r, d, plot_hist);

    // ---------------------------------------------------------------- TIFF and CSV
}

/// `save_tiff`, `load_tiff`: float32 TIFF for Fiji/ImageJ.
fn bind_tiff(r: &mut Registrar) {
    let d = Doc::func("save_tiff")
        .arg(
            "img",
            "Image",
            "",
            "an image (a Scan channel, a sensitivity map…)",
        )
        .arg("path", "string", "", ".tif file (overwritten)")
        .returns("string", "the path written")
        .summary(
            "32-bit float grayscale TIFF that Fiji/ImageJ opens (pixel size in µm in the tags)",
        )
        .example(
            &format!("{SCENE} let p = dir + \"/ex.tif\"; save_tiff(sc.sx, p); load_tiff(p).cols"),
            "21",
        );
    r.bind_ctx(d, |c| {
        move |i: ImageRef, path: &str| save_tiff(&c, &i, path)
    });

    let d = Doc::func("load_tiff")
        .arg("path", "string", "", "a TIFF written by save_tiff")
        .returns("Image", "")
        .summary("read a float32 TIFF back into an Image")
        .example(
            "load_tiff(\"no/such.tif\")",
            "error: load_tiff: no/such.tif",
        );
    r.bind(d, |path: &str| load_tiff(path));
}

/// `save_csv`: profiles and tables as CSV.
fn bind_save_csv(r: &mut Registrar) {
    let d = Doc::func("save_csv")
        .arg("data", "Profile | map", "", "a Profile (two columns) or a table #{column: [numbers], …} (columns of equal length, in key order)")
        .arg("path", "string", "", ".csv file (overwritten)")
        .returns("string", "the path written")
        .summary("CSV for spreadsheets and numpy.loadtxt(delimiter=\",\", skiprows=1)")
        .example(&format!("{SCENE} let p = dir + \"/ex.csv\"; save_csv(sc.sx.row(10), p) == p"), "true")
        .example("let p = status().data_dir + \"/ex_t.csv\"; save_csv(#{d_nm: [50.0, 60.0], sens: [0.1, 0.2]}, p) == p", "true")
        .example("save_csv(#{a: [1.0], b: [1.0, 2.0]}, status().data_dir + \"/ex_bad.csv\")", "error: ");
    r.bind_ctx(d, |c| move |v: Dynamic, path: &str| save_csv(&c, &v, path));
}

/// Bind a figure binding `name(what, path[, opts])` and its form without `opts`: both read the
/// options (without `opts`: every option takes its default), prepare the path (`overwrite`),
/// `draw(ctx, opts, what, path)` and stamp the figure with its provenance; they return the path.
/// The path argument of a figure binding.
const FIGURE_FILE: &str = "figure file, .png or .svg";

/// The declaration of a figure binding after its subject (its one argument, `what`): the path
/// of the figure file (`path`: its help), the form `name(what, path) -> string`, the path
/// written returned.
trait FigureDoc {
    fn figure_file(self, path: &str) -> Doc;
}

impl FigureDoc for Doc {
    fn figure_file(self, path: &str) -> Doc {
        let form = format!("{}({}, path) -> string", self.name, self.params[0].name);
        self.arg("path", "string", "", path)
            .form(&form)
            .returns("string", "the path written")
    }
}

fn bind_figure<T: super::registry::Value>(
    r: &mut Registrar,
    d: Doc,
    draw: fn(&Ctx, &Opts, T, &str) -> RResult<()>,
) {
    let ctx = r.ctx();
    let name = d.name.clone();
    let spec = Arc::new(d.spec());
    let (c, s) = (ctx.clone(), spec.clone());
    r.bind(d, move |v: T, path: &str, m: Map| {
        figure(&c, &s, draw, v, path, &m)
    });
    r.overload(&name, move |v: T, path: &str| {
        figure(&ctx, &spec, draw, v, path, &Map::new())
    });
}

/// A figure binding's call: its options, the path prepared, the drawing, the provenance stamp.
fn figure<T>(
    c: &Ctx,
    spec: &Spec,
    draw: fn(&Ctx, &Opts, T, &str) -> RResult<()>,
    v: T,
    path: &str,
    m: &Map,
) -> RResult<String> {
    let o = Opts::new(spec, m)?;
    let path = &prepare(c, &spec.name, path, o.bool_or(OVERWRITE, false)?)?;
    draw(c, &o, v, path)?;
    stamp(c, path)
}

/// `save_tiff(img, path)`: a 32-bit float grayscale TIFF (pixel size in µm in the tags).
fn save_tiff(c: &Ctx, i: &ImageRef, path: &str) -> RResult<String> {
    let path = &prepare(c, "save_tiff", path, false)?;
    crate::data::tiff::save_tiff(path, &i.0).map_err(|e| ferr("save_tiff", path, e))?;
    stamp(c, path)
}

/// `load_tiff(path)`: a float32 TIFF back into an Image.
fn load_tiff(path: &str) -> RResult<ImageRef> {
    let i = crate::data::tiff::load_tiff(path).map_err(|e| ferr("load_tiff", path, e))?;
    Ok(ImageRef(Arc::new(i)))
}

/// `save_csv(data, path)`: a Profile as two columns, or a map of equal-length number columns (in
/// key order), as CSV with a header line.
fn save_csv(c: &Ctx, v: &Dynamic, path: &str) -> RResult<String> {
    let who = "save_csv";
    let path = &prepare(c, who, path, false)?;
    if let Some(p) = v.read_lock::<ProfileRef>() {
        crate::data::csv::save_csv_profile(path, &p.0).map_err(|e| ferr(who, path, e))?;
    } else if let Some(m) = v.read_lock::<Map>() {
        let mut heads = vec![];
        let mut cols = vec![];
        for (k, col) in m.iter() {
            heads.push(k.to_string());
            cols.push(numbers(who, k, col)?);
        }
        crate::data::csv::save_csv_table(path, &heads, &cols).map_err(|e| ferr(who, path, e))?;
    } else {
        return fail(format!(
            "{who}: data must be a Profile or a map of columns, got {}",
            v.type_name()
        ));
    }
    stamp(c, path)
}

/// `plot(what, path[, opts])`: a heat map with colour bar and µm axes of a scan (Sx, Sy, Sz
/// panels, or one `channel`) or of one image.
fn plot(c: &Ctx, o: &Opts, v: Dynamic, path: &str) -> RResult<()> {
    let who = "plot";
    let title = o.string(TITLE)?.unwrap_or_default();
    let image_opts = |o: &Opts, default_label: &str| -> RResult<PlotOpts> {
        let mut p = match o.string(COLORMAP)?.as_deref() {
            None | Some("sequential") => PlotOpts {
                label: default_label.into(),
                ..PlotOpts::default()
            },
            Some("diverging") => PlotOpts::diverging(default_label),
            Some(c) => {
                return fail(format!(
                    "{who}: colormap = \"{c}\" is not one of \"diverging\", \"sequential\""
                ))
            }
        };
        if let Some(l) = o.string(LABEL)? {
            p.label = l;
        }
        if let Some((a, b)) = o.range(RANGE)? {
            if a.partial_cmp(&b) != Some(std::cmp::Ordering::Less) {
                return fail(format!("{who}: range = [{a}, {b}] must have lo < hi"));
            }
            p.range = Some((a, b));
        }
        Ok(p.with_title(&title))
    };
    if let Some(s) = v.read_lock::<ScanRef>() {
        if let Some(ch) = o.string(CHANNEL)? {
            let img = match ch.as_str() {
                "sx" => &s.scan.sx,
                "sy" => &s.scan.sy,
                "sz" => &s.scan.sz,
                _ => {
                    return fail(format!(
                        "{who}: channel = \"{ch}\" is not one of \"sx\", \"sy\", \"sz\""
                    ))
                }
            };
            let mut p = PlotOpts::for_channel(&ch).with_title(&title);
            if let Some(l) = o.string(LABEL)? {
                p.label = l;
            }
            if let Some((a, b)) = o.range(RANGE)? {
                p.range = Some((a, b));
            }
            plot_image(path, img, &p).map_err(|e| ferr(who, path, e))?;
        } else {
            let so = ScanPlotOpts {
                title,
                include_sz: o.bool_or(INCLUDE_SZ, true)?,
                shared_xy_scale: o.bool_or(SHARED_XY_SCALE, false)?,
            };
            plot_scan(path, &s.scan, &so).map_err(|e| ferr(who, path, e))?;
            let left_out = crate::plot::empty_channels(&s.scan, so.include_sz);
            if !left_out.is_empty() {
                c.log(&format!(
                    "{who}: {} left out of {path}: no data (all {} pixels NaN; a digitiser with fewer inputs records no {})",
                    left_out.join(", "),
                    s.scan.sx.data.len(),
                    left_out.join(", ")
                ));
            }
        }
    } else if let Some(i) = v.read_lock::<ImageRef>() {
        let p = image_opts(o, "")?;
        plot_image(path, &i.0, &p).map_err(|e| ferr(who, path, e))?;
    } else {
        return fail(format!(
            "{who}: what must be a Scan or an Image, got {}",
            v.type_name()
        ));
    }
    Ok(())
}

/// `plot_profile(profiles, path[, opts])`: one or more profiles as lines with a legend (labels:
/// the map's keys, or 1, 2, … for an array).
fn plot_profile(_c: &Ctx, o: &Opts, v: Dynamic, path: &str) -> RResult<()> {
    let who = "plot_profile";
    let mut list: Vec<(String, Arc<crate::data::Profile>)> = vec![];
    let bad = |x: &Dynamic| -> RResult<()> {
        fail(format!(
            "{who}: profiles must be Profile values, got {}",
            x.type_name()
        ))
    };
    if let Some(p) = v.read_lock::<ProfileRef>() {
        list.push((String::new(), p.0.clone()));
    } else if let Some(a) = v.read_lock::<Array>() {
        for (i, x) in a.iter().enumerate() {
            match x.read_lock::<ProfileRef>() {
                Some(p) => list.push((format!("{}", i + 1), p.0.clone())),
                None => bad(x)?,
            }
        }
    } else if let Some(mp) = v.read_lock::<Map>() {
        for (k, x) in mp.iter() {
            match x.read_lock::<ProfileRef>() {
                Some(p) => list.push((k.to_string(), p.0.clone())),
                None => bad(x)?,
            }
        }
    } else {
        bad(&v)?;
    }
    let refs: Vec<(&str, &crate::data::Profile)> =
        list.iter().map(|(l, p)| (l.as_str(), p.as_ref())).collect();
    figure::plot_profile(path, &refs, &xy_opts(o)?).map_err(|e| ferr(who, path, e))?;
    Ok(())
}

/// `plot_xy(series, path[, opts])`: x–y curves and points, with error bars `yerr`.
fn plot_xy(_c: &Ctx, o: &Opts, a: Array, path: &str) -> RResult<()> {
    let who = "plot_xy";
    let mut series = vec![];
    for (i, s) in a.iter().enumerate() {
        let Some(sm) = s.read_lock::<Map>() else {
            return fail(format!(
                "{who}: series[{i}] must be #{{x, y, label, style, yerr}}, got {}",
                s.type_name()
            ));
        };
        for k in sm.keys() {
            if !["x", "y", LABEL.name, "style", "yerr"].contains(&k.as_str()) {
                return fail(format!(
                    "{who}: series[{i}]: unknown key `{k}`; allowed keys: x, y, label, style, yerr"
                ));
            }
        }
        let get = |k: &str| -> RResult<Vec<f64>> {
            match sm.get(k) {
                Some(v) => numbers(who, &format!("series[{i}].{k}"), v),
                None => fail(format!("{who}: series[{i}] lacks `{k}`")),
            }
        };
        let (x, y) = (get("x")?, get("y")?);
        if x.len() != y.len() {
            return fail(format!(
                "{who}: series[{i}]: x and y differ in length ({} vs {})",
                x.len(),
                y.len()
            ));
        }
        let label = sm
            .get(LABEL.name)
            .map(|v| v.to_string())
            .unwrap_or_default();
        let style = match sm.get("style").map(|v| v.to_string()).as_deref() {
            None | Some("line") => SeriesStyle::Line,
            Some("points") => SeriesStyle::Points,
            Some("linepoints") => SeriesStyle::LinePoints,
            Some(s) => {
                return fail(format!(
                    "{who}: series[{i}].style = \"{s}\" is not one of \"line\", \"points\", \"linepoints\""
                ))
            }
        };
        let mut se = Series::line(&label, x, y).with_style(style);
        if sm.contains_key("yerr") {
            let e = get("yerr")?;
            if e.len() != se.y.len() {
                return fail(format!(
                    "{who}: series[{i}]: yerr has {} values for {} points",
                    e.len(),
                    se.y.len()
                ));
            }
            se = se.with_yerr(e);
        }
        series.push(se);
    }
    if series.is_empty() {
        return fail(format!("{who}: series is empty"));
    }
    figure::plot_xy(path, &series, &xy_opts(o)?).map_err(|e| ferr(who, path, e))?;
    Ok(())
}

/// `plot_hist(values, path[, opts])`: a histogram figure of the values in `bins` equal bins
/// (default [`PLOT_HIST_BINS`]).
fn plot_hist(_c: &Ctx, o: &Opts, a: Array, path: &str) -> RResult<()> {
    let who = "plot_hist";
    let v = numbers(who, "values", &Dynamic::from_array(a))?;
    let bins = o.int(BINS)?.unwrap_or(PLOT_HIST_BINS);
    if !(1..=MAX_BINS as i64).contains(&bins) {
        return fail(format!(
            "{who}: bins = {bins} is out of range: 1 ≤ bins ≤ {MAX_BINS}"
        ));
    }
    let xo = XyOpts {
        title: o.string(TITLE)?.unwrap_or_default(),
        xlabel: o.string(XLABEL)?.unwrap_or_default(),
        ylabel: o.string(YLABEL)?.unwrap_or_default(),
        ..XyOpts::default()
    };
    figure::plot_hist(path, &v, bins as usize, &xo).map_err(|e| ferr(who, path, e))?;
    Ok(())
}
