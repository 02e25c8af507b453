//! Figures with plotters: heat maps of images and scans, line profiles, histograms and x–y
//! plots (linear or log axes, error bars). PNG, or SVG when the path ends in `.svg`.
//!
//! Text uses DejaVu Sans embedded in the binary (`src/plot/fonts/`), registered once with
//! plotters' `ab_glyph` backend, so no system font is needed (without a registered font plotters
//! writes blank images without any error). Files are written to a temporary name and renamed.
//! Bad input (empty data, all-NaN images, non-positive values on a log axis, a missing folder,
//! an unknown extension) gives an `Err` naming the problem; nothing panics.
//!
//! Conventions: heat maps put the first axis value at the bottom-left (y up, as in the paper's
//! figures), pixels are square in µm when both axes have the same spacing, NaN pixels are grey.

mod axis;
mod colormap;

pub use axis::{nice_ticks, AxisCoord};
pub use colormap::{Colormap, NAN_RGB};

use crate::analysis::stats::histogram;
use crate::data::{atomic_write, DataError, Image, Profile, Scan, ScanStatus};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::Path;
use std::sync::OnceLock;

/// The embedded font (DejaVu Sans, Bitstream Vera licence: `src/plot/fonts/DejaVuSans-LICENSE.txt`).
pub static FONT_TTF: &[u8] = include_bytes!("fonts/DejaVuSans.ttf");

/// Font family name used by every figure.
pub const FONT: &str = "sans-serif";

/// Register the embedded font with plotters (once per process).
pub fn ensure_font() -> Result<(), String> {
    static DONE: OnceLock<Result<(), String>> = OnceLock::new();
    DONE.get_or_init(|| {
        plotters::style::register_font(FONT, FontStyle::Normal, FONT_TTF)
            .map_err(|_| "the embedded font could not be loaded".to_string())
    })
    .clone()
}

// ---------------------------------------------------------------- options

/// Options for a heat map of one image.
#[derive(Debug, Clone, PartialEq)]
pub struct PlotOpts {
    /// Figure title (empty: none).
    pub title: String,
    /// What the colour bar shows, e.g. `"Sx"` or `"Sx (V)"`.
    pub label: String,
    pub colormap: Colormap,
    /// Colour range symmetric about 0 (`-m..m` with `m` the largest |value|).
    pub symmetric: bool,
    /// Fixed colour range `(vmin, vmax)`; overrides `symmetric`.
    pub range: Option<(f64, f64)>,
}

impl Default for PlotOpts {
    fn default() -> Self {
        PlotOpts {
            title: String::new(),
            label: String::new(),
            colormap: Colormap::Sequential,
            symmetric: false,
            range: None,
        }
    }
}

impl PlotOpts {
    /// The usual choice for a channel: diverging and symmetric for `sx`/`sy` (signed
    /// difference signals), sequential for `sz` and anything else.
    pub fn for_channel(channel: &str) -> PlotOpts {
        match channel.to_ascii_lowercase().as_str() {
            "sx" | "x" => PlotOpts::diverging("Sx"),
            "sy" | "y" => PlotOpts::diverging("Sy"),
            "sz" | "z" => PlotOpts {
                label: "Sz".into(),
                ..PlotOpts::default()
            },
            other => PlotOpts {
                label: other.to_string(),
                ..PlotOpts::default()
            },
        }
    }

    /// Diverging, symmetric about zero, with this colour-bar label.
    pub fn diverging(label: &str) -> PlotOpts {
        PlotOpts {
            label: label.into(),
            colormap: Colormap::Diverging,
            symmetric: true,
            ..PlotOpts::default()
        }
    }

    pub fn with_title(mut self, title: &str) -> PlotOpts {
        self.title = title.into();
        self
    }
}

/// Options for [`plot_scan`].
#[derive(Debug, Clone, PartialEq)]
pub struct ScanPlotOpts {
    pub title: String,
    /// Also draw the Sz panel.
    pub include_sz: bool,
    /// Sx and Sy on one common symmetric colour range (compare magnitudes); otherwise each
    /// panel has its own.
    pub shared_xy_scale: bool,
}

impl Default for ScanPlotOpts {
    fn default() -> Self {
        ScanPlotOpts {
            title: String::new(),
            include_sz: true,
            shared_xy_scale: false,
        }
    }
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SeriesStyle {
    Line,
    Points,
    LinePoints,
    /// A dashed line (a bound drawn over the curve that reaches it stays visible).
    Dashed,
}

/// One curve of an x–y plot. NaN points are skipped (lines break there).
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub label: String,
    pub x: Vec<f64>,
    pub y: Vec<f64>,
    /// Symmetric error bars (± yerr), same length as `y`.
    pub yerr: Option<Vec<f64>>,
    pub style: SeriesStyle,
}

impl Series {
    pub fn line(label: &str, x: Vec<f64>, y: Vec<f64>) -> Series {
        Series {
            label: label.into(),
            x,
            y,
            yerr: None,
            style: SeriesStyle::Line,
        }
    }
    pub fn points(label: &str, x: Vec<f64>, y: Vec<f64>) -> Series {
        Series {
            label: label.into(),
            x,
            y,
            yerr: None,
            style: SeriesStyle::Points,
        }
    }
    pub fn with_yerr(mut self, yerr: Vec<f64>) -> Series {
        self.yerr = Some(yerr);
        self
    }
    pub fn with_style(mut self, style: SeriesStyle) -> Series {
        self.style = style;
        self
    }
}

/// Options for line plots, histograms and x–y plots.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct XyOpts {
    pub title: String,
    /// Axis labels; empty means a default (profiles: `"<axis> (µm)"`, histograms: `"count"`).
    pub xlabel: String,
    pub ylabel: String,
    pub log_x: bool,
    pub log_y: bool,
}

impl XyOpts {
    pub fn new(title: &str, xlabel: &str, ylabel: &str) -> XyOpts {
        XyOpts {
            title: title.into(),
            xlabel: xlabel.into(),
            ylabel: ylabel.into(),
            ..XyOpts::default()
        }
    }
    pub fn log_log(mut self) -> XyOpts {
        self.log_x = true;
        self.log_y = true;
        self
    }
}

// ---------------------------------------------------------------- output

/// Output format chosen from the file extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Format {
    Png,
    Svg,
}

fn output_format(path: &Path) -> Result<Format, DataError> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    match ext.as_deref() {
        Some("png") => Ok(Format::Png),
        Some("svg") => Ok(Format::Svg),
        _ => Err(DataError::invalid(
            "path",
            format!("{:?}", path.display().to_string()),
            "figure files end in .png or .svg",
        )),
    }
}

/// Something that can be drawn on any plotters backend.
trait Figure {
    fn size(&self) -> (u32, u32);
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String>;
}

fn perr<E: std::fmt::Display>(e: E) -> String {
    e.to_string()
}

fn render<F: Figure>(path: &Path, fig: &F) -> Result<(), DataError> {
    let format = output_format(path)?;
    let plot_err = |msg: String| DataError::Plot {
        path: path.to_path_buf(),
        msg,
    };
    ensure_font().map_err(plot_err)?;
    atomic_write(path, |tmp| {
        // Safety net: a panic inside the drawing library becomes an error, not a crash.
        let run = || -> Result<(), String> {
            match format {
                Format::Png => {
                    let (w, h) = fig.size();
                    let mut rgb = vec![0u8; w as usize * h as usize * 3];
                    {
                        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
                        root.fill(&WHITE).map_err(perr)?;
                        fig.draw(&root)?;
                        root.present().map_err(perr)?;
                    }
                    write_png(tmp, w, h, &rgb)
                }
                Format::Svg => {
                    let root = SVGBackend::new(tmp, fig.size()).into_drawing_area();
                    root.fill(&WHITE).map_err(perr)?;
                    fig.draw(&root)?;
                    root.present().map_err(perr)
                }
            }
        };
        match std::panic::catch_unwind(std::panic::AssertUnwindSafe(run)) {
            Ok(r) => r.map_err(plot_err),
            Err(_) => Err(plot_err("internal error in the plotting library".into())),
        }
    })
}

/// Encode an 8-bit RGB raster (rows top to bottom) as a PNG file (the `png` crate: plotters'
/// own encoder would pull in the whole `image` crate for this one call).
fn write_png(path: &Path, w: u32, h: u32, rgb: &[u8]) -> Result<(), String> {
    let file = std::fs::File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc.write_header().map_err(perr)?;
    writer.write_image_data(rgb).map_err(perr)?;
    writer.finish().map_err(perr)
}

// ---------------------------------------------------------------- styles

const TITLE_PX: u32 = 22;
const DESC_PX: u32 = 17;
const TICK_PX: u32 = 14;

fn font(px: u32) -> TextStyle<'static> {
    TextStyle::from((FONT, px).into_font()).color(&BLACK)
}

fn rgb((r, g, b): (u8, u8, u8)) -> RGBColor {
    RGBColor(r, g, b)
}

/// Series colours: d3's Category10, matplotlib's "tab10" (the `colorous` crate's table).
fn series_color(k: usize) -> RGBColor {
    let c = colorous::CATEGORY10[k % colorous::CATEGORY10.len()];
    RGBColor(c.r, c.g, c.b)
}

/// Draw centred text in a strip (used for titles).
fn draw_centered<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    text: &str,
    px: u32,
) -> Result<(), String> {
    let (w, h) = area.dim_in_pixel();
    let style = font(px).pos(Pos::new(HPos::Center, VPos::Center));
    area.draw(&Text::new(
        text.to_string(),
        (w as i32 / 2, h as i32 / 2),
        style,
    ))
    .map_err(perr)
}

// ---------------------------------------------------------------- heat maps

/// Pixel edges of an axis of pixel centres (midpoints; ends extrapolated). A single pixel
/// gets width `fallback`.
fn pixel_edges(a: &[f64], fallback: f64) -> Vec<f64> {
    match a.len() {
        0 => vec![],
        1 => vec![a[0] - fallback / 2.0, a[0] + fallback / 2.0],
        n => {
            let mut e = Vec::with_capacity(n + 1);
            e.push(a[0] - (a[1] - a[0]) / 2.0);
            for k in 1..n {
                e.push((a[k - 1] + a[k]) / 2.0);
            }
            e.push(a[n - 1] + (a[n - 1] - a[n - 2]) / 2.0);
            e
        }
    }
}

fn pixel_width_fallback(img: &Image) -> (f64, f64) {
    let (dx, dy) = (img.dx().abs(), img.dy().abs());
    let fx = if dx > 0.0 {
        dx
    } else if dy > 0.0 {
        dy
    } else {
        1.0
    };
    let fy = if dy > 0.0 { dy } else { fx };
    (fx, fy)
}

fn extents(img: &Image) -> ((f64, f64), (f64, f64)) {
    let (fx, fy) = pixel_width_fallback(img);
    let ex = pixel_edges(&img.x, fx);
    let ey = pixel_edges(&img.y, fy);
    let span = |e: &[f64]| {
        let (a, b) = (e[0], e[e.len() - 1]);
        (a.min(b), a.max(b))
    };
    (span(&ex), span(&ey))
}

/// Size in screen pixels of the heat-map plotting area for `img` when its longer side gets
/// `long_side` pixels: proportional to the extents in µm, so pixels are square in µm when the
/// axes have equal spacing. Images more elongated than 4:1 (line scans) are stretched so that
/// the shorter side keeps a quarter of the longer one (room for ticks and the colour bar).
pub fn image_plot_area(img: &Image, long_side: u32) -> (u32, u32) {
    let ((x0, x1), (y0, y1)) = extents(img);
    let (ex, ey) = (x1 - x0, y1 - y0);
    let m = ex.max(ey);
    let min_side = (long_side / 4).max(40);
    let w = ((f64::from(long_side) * ex / m).round() as u32).max(min_side);
    let h = ((f64::from(long_side) * ey / m).round() as u32).max(min_side);
    (w, h)
}

/// Number of ticks for an axis `len` screen pixels long, one per `per` pixels (2 to 6).
fn ticks_for(len: u32, per: u32) -> usize {
    ((len / per) as usize).clamp(2, 6)
}

/// Colour range of a heat map, validated.
fn color_range(img: &Image, opts: &PlotOpts, what: &str) -> Result<(f64, f64), String> {
    if img.data.is_empty() {
        return Err(format!("{what} is empty (no pixels)"));
    }
    if let Some((a, b)) = opts.range {
        if !(a.is_finite() && b.is_finite() && a < b) {
            return Err(format!(
                "colour range ({a}, {b}) must be two finite numbers with vmin < vmax"
            ));
        }
        return Ok((a, b));
    }
    let (lo, hi) = match (img.min(), img.max()) {
        (Ok(lo), Ok(hi)) => (lo, hi),
        _ => {
            return Err(format!(
                "{what} has no data: all {} pixels are NaN",
                img.data.len()
            ))
        }
    };
    if !lo.is_finite() || !hi.is_finite() {
        return Err(format!(
            "{what} contains infinite values (min {lo}, max {hi})"
        ));
    }
    let (mut lo, mut hi) = if opts.symmetric {
        let m = lo.abs().max(hi.abs());
        (-m, m)
    } else {
        (lo, hi)
    };
    if lo >= hi {
        let pad = if lo == 0.0 { 1.0 } else { lo.abs() * 0.5 };
        lo -= pad;
        hi += pad;
    }
    Ok((lo, hi))
}

/// One heat map with its colour bar, laid out in fixed pixel sizes.
struct HeatPanel<'a> {
    img: &'a Image,
    colormap: Colormap,
    vmin: f64,
    vmax: f64,
    label: String,
    caption: String,
    plot_w: u32,
    plot_h: u32,
}

const H_CAPTION: u32 = 34;
const H_TOP: u32 = 10;
const H_LEFT: u32 = 78;
const H_BOTTOM: u32 = 58;
const CB_GAP: u32 = 18;
const CB_W: u32 = 22;
const CB_LABELS: u32 = 70;
const H_RIGHT: u32 = 26;
/// Room left of the y label area for the rotated axis description.
const H_MARGIN_LEFT: u32 = 16;
const TICK_MARK: i32 = 5;

impl HeatPanel<'_> {
    fn size(&self) -> (u32, u32) {
        let cap = if self.caption.is_empty() {
            0
        } else {
            H_CAPTION
        };
        (
            H_MARGIN_LEFT + H_LEFT + self.plot_w + CB_GAP + CB_W + CB_LABELS + H_RIGHT,
            cap + H_TOP + self.plot_h + H_BOTTOM,
        )
    }

    fn draw<DB: DrawingBackend>(&self, area: &DrawingArea<DB, Shift>) -> Result<(), String> {
        let area = if self.caption.is_empty() {
            area.clone()
        } else {
            let (cap, rest) = area.split_vertically(H_CAPTION);
            draw_centered(&cap, &self.caption, DESC_PX + 1)?;
            rest
        };
        let (main, bar) = area.split_horizontally(H_MARGIN_LEFT + H_LEFT + self.plot_w);
        let img = self.img;
        let ((x0, x1), (y0, y1)) = extents(img);
        let (nx, ny) = (ticks_for(self.plot_w, 80), ticks_for(self.plot_h, 60));
        let mut chart = ChartBuilder::on(&main)
            .margin_top(H_TOP)
            .margin_left(H_MARGIN_LEFT)
            .x_label_area_size(H_BOTTOM)
            .y_label_area_size(H_LEFT)
            .build_cartesian_2d(AxisCoord::linear(x0, x1, nx), AxisCoord::linear(y0, y1, ny))
            .map_err(perr)?;
        chart
            .configure_mesh()
            .disable_mesh()
            .set_all_tick_mark_size(TICK_MARK)
            .x_desc(format!("{} (µm)", img.x_name))
            .y_desc(format!("{} (µm)", img.y_name))
            .label_style(font(TICK_PX))
            .axis_desc_style(font(DESC_PX))
            .draw()
            .map_err(perr)?;

        let (fx, fy) = pixel_width_fallback(img);
        let ex = pixel_edges(&img.x, fx);
        let ey = pixel_edges(&img.y, fy);
        let (vmin, vmax, cmap) = (self.vmin, self.vmax, self.colormap);
        let rects = img.data.indexed_iter().map(|((i, j), &v)| {
            let c = rgb(cmap.rgb_value(v, vmin, vmax));
            Rectangle::new([(ex[j], ey[i]), (ex[j + 1], ey[i + 1])], c.filled())
        });
        chart.draw_series(rects).map_err(perr)?;
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(x0, y0), (x1, y1)],
                BLACK.stroke_width(1),
            )))
            .map_err(perr)?;

        // Colour bar.
        let mut cb = ChartBuilder::on(&bar)
            .margin_top(H_TOP)
            .margin_left(CB_GAP)
            .margin_right(H_RIGHT)
            .x_label_area_size(H_BOTTOM)
            .right_y_label_area_size(CB_LABELS)
            .build_cartesian_2d(
                AxisCoord::linear(0.0, 1.0, 2),
                AxisCoord::linear(vmin, vmax, ny),
            )
            .map_err(perr)?;
        cb.configure_mesh()
            .disable_mesh()
            .set_all_tick_mark_size(TICK_MARK)
            .disable_x_axis()
            .y_desc(self.label.clone())
            .label_style(font(TICK_PX))
            .axis_desc_style(font(DESC_PX))
            .draw()
            .map_err(perr)?;
        let steps = 256;
        let bars = (0..steps).map(|k| {
            let a = vmin + (vmax - vmin) * k as f64 / steps as f64;
            let b = vmin + (vmax - vmin) * (k + 1) as f64 / steps as f64;
            let c = rgb(cmap.rgb((k as f64 + 0.5) / steps as f64));
            Rectangle::new([(0.0, a), (1.0, b)], c.filled())
        });
        cb.draw_series(bars).map_err(perr)?;
        cb.draw_series(std::iter::once(Rectangle::new(
            [(0.0, vmin), (1.0, vmax)],
            BLACK.stroke_width(1),
        )))
        .map_err(perr)?;
        Ok(())
    }
}

struct HeatFigure<'a> {
    title: String,
    panels: Vec<HeatPanel<'a>>,
}

const TITLE_H: u32 = 40;

impl Figure for HeatFigure<'_> {
    fn size(&self) -> (u32, u32) {
        let w: u32 = self.panels.iter().map(|p| p.size().0).sum();
        let h = self.panels.iter().map(|p| p.size().1).max().unwrap_or(100);
        (w + 10, h + if self.title.is_empty() { 0 } else { TITLE_H })
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String> {
        let mut area = if self.title.is_empty() {
            root.clone()
        } else {
            let (t, rest) = root.split_vertically(TITLE_H);
            draw_centered(&t, &self.title, TITLE_PX)?;
            rest
        };
        for p in &self.panels {
            let (left, rest) = area.split_horizontally(p.size().0);
            p.draw(&left)?;
            area = rest;
        }
        Ok(())
    }
}

fn nan_note(img: &Image) -> String {
    match img.nan_count() {
        0 => String::new(),
        1 => "1 pixel without data (grey)".into(),
        n => format!("{n} pixels without data (grey)"),
    }
}

fn join_nonempty(parts: &[&str], sep: &str) -> String {
    parts
        .iter()
        .filter(|s| !s.is_empty())
        .copied()
        .collect::<Vec<_>>()
        .join(sep)
}

/// Heat map of one image with µm axes and a colour bar. NaN pixels are grey.
pub fn plot_image(path: impl AsRef<Path>, img: &Image, opts: &PlotOpts) -> Result<(), DataError> {
    let path = path.as_ref();
    output_format(path)?;
    let what = if opts.label.is_empty() {
        "image".to_string()
    } else {
        opts.label.clone()
    };
    let (vmin, vmax) = color_range(img, opts, &what).map_err(|m| plot_error(path, m))?;
    let (plot_w, plot_h) = image_plot_area(img, 480);
    let note = nan_note(img);
    let panel = HeatPanel {
        img,
        colormap: opts.colormap,
        vmin,
        vmax,
        label: opts.label.clone(),
        caption: if opts.title.is_empty() {
            String::new()
        } else {
            note.clone()
        },
        plot_w,
        plot_h,
    };
    let title = if opts.title.is_empty() {
        note
    } else {
        opts.title.clone()
    };
    render(
        path,
        &HeatFigure {
            title,
            panels: vec![panel],
        },
    )
}

/// Sx, Sy (and Sz) of a scan side by side, each with its colour bar: Sx/Sy diverging and
/// symmetric about 0, Sz sequential. Aborted or failed scans say so in the title.
pub fn plot_scan(
    path: impl AsRef<Path>,
    scan: &Scan,
    opts: &ScanPlotOpts,
) -> Result<(), DataError> {
    let path = path.as_ref();
    output_format(path)?;
    let mut channels: Vec<(&Image, PlotOpts)> = vec![
        (&scan.sx, PlotOpts::for_channel("sx")),
        (&scan.sy, PlotOpts::for_channel("sy")),
    ];
    if opts.include_sz {
        channels.push((&scan.sz, PlotOpts::for_channel("sz")));
    }
    // A channel without any finite pixel (a 2-input digitiser gives no Sz) is left out, and the
    // title says so; no channel with data is an error.
    let left_out = empty_channels(scan, opts.include_sz);
    if left_out.len() == channels.len() {
        return Err(plot_error(
            path,
            format!(
                "the scan has no data: all {} pixels of {} are NaN",
                scan.sx.data.len(),
                left_out.join(", ")
            ),
        ));
    }
    channels.retain(|(img, _)| img.data.iter().any(|v| v.is_finite()));
    if opts.shared_xy_scale && channels.len() >= 2 && !left_out.iter().any(|c| *c != "Sz") {
        let m = [&scan.sx, &scan.sy]
            .iter()
            .filter_map(|i| i.abs_max().ok())
            .fold(0.0f64, f64::max);
        if m > 0.0 && m.is_finite() {
            channels[0].1.range = Some((-m, m));
            channels[1].1.range = Some((-m, m));
        }
    }
    let n = channels.len() as u32;
    let long = if n >= 3 { 320 } else { 400 };
    let mut panels = Vec::new();
    for (img, po) in &channels {
        let (vmin, vmax) = color_range(img, po, &po.label).map_err(|m| plot_error(path, m))?;
        let (plot_w, plot_h) = image_plot_area(img, long);
        panels.push(HeatPanel {
            img,
            colormap: po.colormap,
            vmin,
            vmax,
            label: po.label.clone(),
            caption: po.label.clone(),
            plot_w,
            plot_h,
        });
    }
    let status = match scan.status {
        ScanStatus::Complete => String::new(),
        s => format!("scan {s}"),
    };
    let skipped = if left_out.is_empty() {
        String::new()
    } else {
        format!("{} left out: no data", left_out.join(", "))
    };
    let title = join_nonempty(
        &[&opts.title, &status, &nan_note(&scan.sx), &skipped],
        " — ",
    );
    render(path, &HeatFigure { title, panels })
}

/// The channels of a scan (`Sx`, `Sy`, and `Sz` when `include_sz`) without any finite pixel:
/// what [`plot_scan`] leaves out.
pub fn empty_channels(scan: &Scan, include_sz: bool) -> Vec<&'static str> {
    let mut v = vec![("Sx", &scan.sx), ("Sy", &scan.sy)];
    if include_sz {
        v.push(("Sz", &scan.sz));
    }
    v.into_iter()
        .filter(|(_, img)| !img.data.iter().any(|x| x.is_finite()))
        .map(|(n, _)| n)
        .collect()
}

fn plot_error(path: &Path, msg: String) -> DataError {
    DataError::Plot {
        path: path.to_path_buf(),
        msg,
    }
}

// ---------------------------------------------------------------- x–y plots

const XY_W: u32 = 800;
const XY_H: u32 = 560;

/// Axis range with padding; `values` are the finite values to show.
fn data_range(values: &[f64], log: bool, pad: bool) -> (f64, f64) {
    let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if log {
        let (l0, l1) = (lo.log10(), hi.log10());
        let span = l1 - l0;
        let p = if span > 0.0 {
            if pad {
                0.05 * span
            } else {
                0.0
            }
        } else {
            0.3
        };
        (10f64.powf(l0 - p), 10f64.powf(l1 + p))
    } else {
        let span = hi - lo;
        if span > 0.0 {
            let p = if pad { 0.05 * span } else { 0.0 };
            (lo - p, hi + p)
        } else {
            let p = if lo == 0.0 { 1.0 } else { 0.1 * lo.abs() };
            (lo - p, hi + p)
        }
    }
}

fn axis(lo: f64, hi: f64, log: bool, n: usize) -> AxisCoord {
    if log {
        AxisCoord::log(lo, hi)
    } else {
        AxisCoord::linear(lo, hi, n)
    }
}

/// Check the series and return all finite (x, y±err) values for the axis ranges.
fn validate_series(series: &[Series], opts: &XyOpts) -> Result<(Vec<f64>, Vec<f64>), String> {
    if series.is_empty() {
        return Err("no series to plot (empty list)".into());
    }
    let (mut xs, mut ys) = (Vec::new(), Vec::new());
    for s in series {
        let name = if s.label.is_empty() {
            "(unlabelled)".to_string()
        } else {
            format!("{:?}", s.label)
        };
        if s.x.len() != s.y.len() {
            return Err(format!(
                "series {name}: x has {} values but y has {}",
                s.x.len(),
                s.y.len()
            ));
        }
        if let Some(e) = &s.yerr {
            if e.len() != s.y.len() {
                return Err(format!(
                    "series {name}: yerr has {} values but y has {}",
                    e.len(),
                    s.y.len()
                ));
            }
            if let Some((k, v)) = e
                .iter()
                .enumerate()
                .find(|(_, v)| **v < 0.0 || v.is_infinite())
            {
                return Err(format!(
                    "series {name}: yerr[{k}] = {v}; error bars must be finite and >= 0"
                ));
            }
        }
        for k in 0..s.x.len() {
            let (x, y) = (s.x[k], s.y[k]);
            for (axis_name, v) in [("x", x), ("y", y)] {
                if v.is_infinite() {
                    return Err(format!(
                        "series {name}: {axis_name}[{k}] = {v}; values must be finite (NaN points are skipped)"
                    ));
                }
            }
            if x.is_nan() || y.is_nan() {
                continue;
            }
            if opts.log_x && x <= 0.0 {
                return Err(format!(
                    "series {name}: x[{k}] = {x}; a log x axis needs x > 0"
                ));
            }
            if opts.log_y && y <= 0.0 {
                return Err(format!(
                    "series {name}: y[{k}] = {y}; a log y axis needs y > 0"
                ));
            }
            xs.push(x);
            ys.push(y);
            if let Some(e) = s.yerr.as_ref().map(|e| e[k]).filter(|e| e.is_finite()) {
                ys.push(y + e);
                if !opts.log_y || y - e > 0.0 {
                    ys.push(y - e);
                }
            }
        }
    }
    if xs.is_empty() {
        return Err("no finite points to plot (all values are NaN or the series are empty)".into());
    }
    Ok((xs, ys))
}

/// Corner for the legend with the fewest data points under it.
fn legend_corner(series: &[Series], xa: &AxisCoord, ya: &AxisCoord) -> SeriesLabelPosition {
    let corners = [
        (SeriesLabelPosition::UpperRight, (0.55, 1.0), (0.65, 1.0)),
        (SeriesLabelPosition::UpperLeft, (0.0, 0.45), (0.65, 1.0)),
        (SeriesLabelPosition::LowerRight, (0.55, 1.0), (0.0, 0.35)),
        (SeriesLabelPosition::LowerLeft, (0.0, 0.45), (0.0, 0.35)),
    ];
    let mut best = (usize::MAX, SeriesLabelPosition::UpperRight);
    for (pos, (x0, x1), (y0, y1)) in corners {
        let mut n = 0;
        for s in series {
            for (&x, &y) in s.x.iter().zip(&s.y) {
                let (fx, fy) = (xa.fraction(x), ya.fraction(y));
                if fx >= x0 && fx <= x1 && fy >= y0 && fy <= y1 {
                    n += 1;
                }
            }
        }
        if n < best.0 {
            best = (n, pos);
        }
    }
    best.1
}

struct XyFigure<'a> {
    series: &'a [Series],
    opts: &'a XyOpts,
    xa: AxisCoord,
    ya: AxisCoord,
    /// Histogram bars (left, right, count) drawn instead of series when present.
    bars: Vec<(f64, f64, f64)>,
    note: String,
}

impl Figure for XyFigure<'_> {
    fn size(&self) -> (u32, u32) {
        (XY_W, XY_H)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String> {
        let area = if self.opts.title.is_empty() {
            root.margin(12, 0, 0, 0)
        } else {
            let (t, rest) = root.split_vertically(TITLE_H);
            draw_centered(&t, &self.opts.title, TITLE_PX)?;
            rest
        };
        let mut chart = ChartBuilder::on(&area)
            .margin_right(28)
            .margin_left(8)
            .x_label_area_size(58)
            .y_label_area_size(88)
            .build_cartesian_2d(self.xa.clone(), self.ya.clone())
            .map_err(perr)?;
        chart
            .configure_mesh()
            .set_all_tick_mark_size(TICK_MARK)
            .x_desc(self.opts.xlabel.clone())
            .y_desc(self.opts.ylabel.clone())
            .label_style(font(TICK_PX))
            .axis_desc_style(font(DESC_PX))
            .bold_line_style(RGBColor(220, 220, 220))
            .light_line_style(RGBColor(242, 242, 242))
            .draw()
            .map_err(perr)?;

        if !self.bars.is_empty() {
            let fill = series_color(0).mix(0.75);
            chart
                .draw_series(
                    self.bars
                        .iter()
                        .filter(|b| b.2 > 0.0)
                        .map(|&(a, b, c)| Rectangle::new([(a, 0.0), (b, c)], fill.filled())),
                )
                .map_err(perr)?;
            chart
                .draw_series(self.bars.iter().filter(|b| b.2 > 0.0).map(|&(a, b, c)| {
                    Rectangle::new([(a, 0.0), (b, c)], series_color(0).stroke_width(1))
                }))
                .map_err(perr)?;
        }

        let mut any_label = false;
        for (k, s) in self.series.iter().enumerate() {
            let color = series_color(k);
            let finite: Vec<(f64, f64, Option<f64>)> = (0..s.x.len())
                .filter(|&i| s.x[i].is_finite() && s.y[i].is_finite())
                .map(|i| {
                    (
                        s.x[i],
                        s.y[i],
                        s.yerr.as_ref().map(|e| e[i]).filter(|e| e.is_finite()),
                    )
                })
                .collect();
            // error bars
            let ylo = self.ya.range().start;
            let bars = finite.iter().filter_map(|&(x, y, e)| {
                e.map(|e| {
                    let lo = if self.opts.log_y && y - e <= 0.0 {
                        ylo
                    } else {
                        y - e
                    };
                    ErrorBar::new_vertical(x, lo, y, y + e, color.stroke_width(1), 8)
                })
            });
            chart.draw_series(bars).map_err(perr)?;
            // lines: one segment per run of finite points
            let mut labelled = false;
            let label_it = |anno: &mut plotters::chart::SeriesAnno<'_, DB>, points: bool| {
                if !s.label.is_empty() {
                    anno.label(s.label.clone());
                    if points {
                        anno.legend(move |(x, y)| Circle::new((x + 10, y), 4, color.filled()));
                    } else {
                        anno.legend(move |(x, y)| {
                            PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                        });
                    }
                }
            };
            if s.style != SeriesStyle::Points {
                for r in finite_runs(&s.x, &s.y) {
                    let anno = if s.style == SeriesStyle::Dashed {
                        chart.draw_series(DashedLineSeries::new(r, 9, 6, color.stroke_width(2)))
                    } else {
                        chart.draw_series(LineSeries::new(r, color.stroke_width(2)))
                    }
                    .map_err(perr)?;
                    if !labelled {
                        label_it(anno, false);
                        labelled = true;
                    }
                }
            }
            if matches!(s.style, SeriesStyle::Points | SeriesStyle::LinePoints) {
                let anno = chart
                    .draw_series(
                        finite
                            .iter()
                            .map(|&(x, y, _)| Circle::new((x, y), 4, color.filled())),
                    )
                    .map_err(perr)?;
                if !labelled {
                    label_it(anno, true);
                    labelled = true;
                }
            }
            if !labelled {
                let anno = chart
                    .draw_series(std::iter::empty::<Circle<(f64, f64), u32>>())
                    .map_err(perr)?;
                label_it(anno, false);
            }
            any_label |= !s.label.is_empty();
        }
        if any_label {
            chart
                .configure_series_labels()
                .position(legend_corner(self.series, &self.xa, &self.ya))
                .background_style(WHITE.mix(0.85))
                .border_style(RGBColor(160, 160, 160))
                .label_font(font(TICK_PX + 1))
                .margin(12)
                .draw()
                .map_err(perr)?;
        }
        if !self.note.is_empty() {
            // Pixel ranges are absolute backend coordinates, which is what `root` uses.
            let (xr, yr) = chart.plotting_area().get_pixel_range();
            let style = font(TICK_PX).pos(Pos::new(HPos::Right, VPos::Top));
            root.draw(&Text::new(
                self.note.clone(),
                (xr.end - 10, yr.start + 10),
                style,
            ))
            .map_err(perr)?;
        }
        Ok(())
    }
}

/// The runs of consecutive points where both x and y are finite (a line is drawn through
/// each run, not across the gaps).
fn finite_runs(x: &[f64], y: &[f64]) -> Vec<Vec<(f64, f64)>> {
    let mut run: Vec<(f64, f64)> = Vec::new();
    let mut runs = Vec::new();
    for (&x, &y) in x.iter().zip(y) {
        if x.is_finite() && y.is_finite() {
            run.push((x, y));
        } else if !run.is_empty() {
            runs.push(std::mem::take(&mut run));
        }
    }
    if !run.is_empty() {
        runs.push(run);
    }
    runs
}

/// Curves `y(x)` with a legend; optional error bars and log axes (for d³ scaling and
/// error-versus-time Pareto plots use `log_x` and `log_y`).
pub fn plot_xy(path: impl AsRef<Path>, series: &[Series], opts: &XyOpts) -> Result<(), DataError> {
    let path = path.as_ref();
    output_format(path)?;
    let (xs, ys) = validate_series(series, opts).map_err(|m| plot_error(path, m))?;
    let (x0, x1) = data_range(&xs, opts.log_x, true);
    let (y0, y1) = data_range(&ys, opts.log_y, true);
    let fig = XyFigure {
        series,
        opts,
        xa: axis(x0, x1, opts.log_x, 8),
        ya: axis(y0, y1, opts.log_y, 6),
        bars: vec![],
        note: String::new(),
    };
    render(path, &fig)
}

/// Line profiles, one curve per `(label, profile)`, with a legend. The x label defaults to
/// `"<axis> (µm)"` from the first profile.
pub fn plot_profile(
    path: impl AsRef<Path>,
    profiles: &[(&str, &Profile)],
    opts: &XyOpts,
) -> Result<(), DataError> {
    let path = path.as_ref();
    if profiles.is_empty() {
        return Err(plot_error(path, "no profiles to plot (empty list)".into()));
    }
    let series: Vec<Series> = profiles
        .iter()
        .map(|(label, p)| Series::line(label, p.t.clone(), p.v.clone()))
        .collect();
    let mut o = opts.clone();
    if o.xlabel.is_empty() {
        o.xlabel = format!("{} (µm)", profiles[0].1.t_name);
    }
    if o.ylabel.is_empty() {
        o.ylabel = "signal".into();
    }
    plot_xy(path, &series, &o)
}

/// Histogram of `values` in `bins` equal bins between the smallest and largest finite value.
/// NaN values are skipped and counted in a note on the figure. Log axes are not supported.
pub fn plot_hist(
    path: impl AsRef<Path>,
    values: &[f64],
    bins: usize,
    opts: &XyOpts,
) -> Result<(), DataError> {
    let path = path.as_ref();
    output_format(path)?;
    if opts.log_x || opts.log_y {
        return Err(plot_error(
            path,
            "histograms are drawn on linear axes (log_x/log_y not supported)".into(),
        ));
    }
    let h = histogram(values, bins, None).map_err(|e| plot_error(path, e.to_string()))?;
    let (counts, finite_n, nan) = (&h.counts, h.count(), h.n_skipped);
    let (lo, hi) = (h.edges[0], h.edges[h.edges.len() - 1]);
    let all_equal = h.all_equal;
    let bins = counts.len();
    let width = (hi - lo) / bins as f64;
    let counts: Vec<f64> = counts.iter().map(|&c| c as f64).collect();
    let bars: Vec<(f64, f64, f64)> = (0..bins)
        .map(|k| {
            (
                lo + width * k as f64,
                lo + width * (k + 1) as f64,
                counts[k],
            )
        })
        .collect();
    let cmax = counts.iter().copied().fold(0.0, f64::max);
    let mut o = opts.clone();
    if o.ylabel.is_empty() {
        o.ylabel = "count".into();
    }
    let mut note = format!("n = {finite_n}");
    if all_equal {
        note += &format!(
            ", all equal to {}",
            crate::data::image::fmt_sig((lo + hi) / 2.0, 6)
        );
    }
    if nan > 0 {
        note += &format!(", {nan} NaN skipped");
    }
    let pad = (hi - lo) * if all_equal { 2.0 } else { 0.02 };
    let fig = XyFigure {
        series: &[],
        opts: &o,
        xa: AxisCoord::linear(lo - pad, hi + pad, if all_equal { 4 } else { 8 }),
        ya: AxisCoord::linear(0.0, cmax * 1.12, 6),
        bars,
        note,
    };
    render(path, &fig)
}
