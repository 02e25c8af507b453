//! Clipped and dark pixels of a scan, and the one check every analysis uses before it trusts
//! them ([`input_check`]).
//!
//! A scan counts, per pixel and channel, the digitiser samples taken at or beyond the input's
//! rail (`acquire::clip`; the range per backend is in `instrument::range`), and marks the
//! pixels whose sum lay below the QPD's floor (laser off, beam blocked). Files keep them as
//! the arrays `clipped_sx`, `clipped_sy`, `clipped_sz` and `dark`, written only when a pixel is
//! clipped (resp. dark), and summarise them in `meta.clipped` and `meta.dark` (docs/files.md).

pub use super::image::{PixelFlags, CLIPPED, DARK};
pub use super::scan::InputFlags;
use super::Scan;
use ndarray::Array2;
use serde_json::json;

/// A digitiser's input range and sum floor, in its own units (volts for hardware, signal units
/// for the simulator).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InputRange {
    /// Samples at or beyond ±`full_scale` are clipped.
    pub full_scale: f64,
    /// The unit of `full_scale` and `sum_floor` (`"V"`; `""` for the simulator's signal units).
    pub unit: String,
    /// The sum input below which a pixel is dark (`None`: no floor checked).
    pub sum_floor: Option<f64>,
    /// The sum signal Sz of a scan back to the sum input: `input = sz / sum_gain + sum_offset`
    /// (the inverse of the calibration `sz = gain · (input − offset)`).
    pub sum_gain: f64,
    pub sum_offset: f64,
}

/// The relative margin under full scale at which a sample counts as at the rail: two steps of
/// a 14-bit converter (the Red Pitaya's; the NI PCI-6120's 16 bits step finer), so that the
/// converter's top code (full scale less one step) counts.
pub const RAIL_MARGIN: f64 = 2.0 / 8192.0;

impl InputRange {
    /// A range of ±`full_scale` `unit` with no sum floor and an identity sum calibration.
    pub fn new(full_scale: f64, unit: &str) -> InputRange {
        InputRange {
            full_scale,
            unit: unit.to_string(),
            sum_floor: None,
            sum_gain: 1.0,
            sum_offset: 0.0,
        }
    }

    /// With a sum floor and the sum's calibration (`sz = gain · (input − offset)`).
    pub fn with_sum(mut self, floor: Option<f64>, gain: f64, offset: f64) -> InputRange {
        self.sum_floor = floor;
        self.sum_gain = if gain.is_finite() && gain != 0.0 {
            gain
        } else {
            1.0
        };
        self.sum_offset = offset;
        self
    }

    /// Is `v` (in the range's units) at or beyond the rail?
    pub fn at_rail(&self, v: f64) -> bool {
        at_rail(v, self.full_scale)
    }

    /// Is a pixel whose mean sum signal is `sz` dark (its sum input below the floor)? NaN
    /// (not measured) is never dark.
    pub fn is_dark(&self, sz: f64) -> bool {
        match self.sum_floor {
            Some(f) if sz.is_finite() => sz / self.sum_gain + self.sum_offset < f,
            _ => false,
        }
    }

    /// `"±0.2 V input range"` (`"±0.5 input range (signal units)"` for the simulator).
    pub fn describe(&self) -> String {
        if self.unit.is_empty() {
            format!("±{} input range (signal units)", sig(self.full_scale))
        } else {
            format!("±{} {} input range", sig(self.full_scale), self.unit)
        }
    }

    /// `"0.02 V on the sum input"`, when there is a floor.
    pub fn describe_floor(&self) -> Option<String> {
        self.sum_floor.map(|f| {
            if self.unit.is_empty() {
                format!("{} (signal units) on the detector's sum", sig(f))
            } else {
                format!("{} {} on the sum input", sig(f), self.unit)
            }
        })
    }
}

/// Is `v` at or beyond ±`full_scale` (within [`RAIL_MARGIN`])? Non-finite values count as
/// clipped (an overflowed converter).
pub fn at_rail(v: f64, full_scale: f64) -> bool {
    !v.is_finite() || v.abs() >= full_scale * (1.0 - RAIL_MARGIN)
}

/// A number in a short form for messages (`0.2`, `1.5e-5`).
fn sig(v: f64) -> String {
    let s = format!("{v}");
    if s.len() <= 8 {
        s
    } else {
        format!("{v:.4e}")
    }
}

/// The file and metadata names of the channels' clip counts.
pub const CLIPPED_ARRAYS: [&str; 3] = ["clipped_sx", "clipped_sy", "clipped_sz"];
const LABELS: [&str; 3] = ["Sx", "Sy", "Sz"];

/// Rows `[r0, r1)` and columns `[c0, c1)` of a scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Region {
    pub rows: (usize, usize),
    pub cols: (usize, usize),
}

/// What an analysis needs to know about the pixels it uses.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct InputCheck {
    /// Clipped pixels of Sx, Sy, Sz (0 for a channel not asked about).
    pub clipped_pixels: [usize; 3],
    /// Dark pixels (the sum below the floor).
    pub dark_pixels: usize,
    /// One plain-language sentence per problem: empty when the pixels are sound.
    pub warnings: Vec<String>,
    /// Set when every pixel used is clipped in a channel used, or dark: no number can be read
    /// from such pixels, and the analysis refuses (the sentence says why).
    pub refusal: Option<String>,
}

impl InputCheck {
    pub fn is_clean(&self) -> bool {
        self.warnings.is_empty()
    }

    /// The warnings for the answer, or the refusal of `who` (`"who: every pixel …"`) when the
    /// pixels cannot carry an answer.
    pub fn gate(self, who: &str) -> Result<Vec<String>, String> {
        match self.refusal {
            Some(r) => Err(format!("{who}: {r}")),
            None => Ok(self.warnings),
        }
    }
}

/// The refusal when all `used` pixels are clipped (`what`: `"of Sx"`) or dark.
fn all_bad(n: usize, used: usize, what: &str, why: &str) -> Option<String> {
    (used > 0 && n == used).then(|| {
        let what = if what.is_empty() {
            format!("{used}")
        } else {
            format!("{used} {what}")
        };
        format!(
            "every pixel it uses ({what}) is {why}: the answer would be meaningless; {}",
            if why.starts_with("dark") {
                "check the laser and the beam path"
            } else {
                "lower the signal or raise the QPD's input range"
            }
        )
    })
}

/// The clipped and dark pixels of `scan` among the `channels` an analysis uses (`"sx"`,
/// `"sy"`, `"sz"`), inside `region` (the whole scan when `None`), with a warning per channel
/// and one for dark pixels, e.g. `"12 pixels of Sx are clipped (at the ±0.2 V input range)"`.
///
/// A scan loaded without the per-pixel arrays but whose `meta.clipped` counts pixels (a file
/// written by hand, or trimmed) is judged by those counts, for the whole scan.
pub fn input_check(scan: &Scan, channels: &[&str], region: Option<Region>) -> InputCheck {
    let in_region = |r: usize, c: usize| {
        region
            .is_none_or(|g| (g.rows.0..g.rows.1).contains(&r) && (g.cols.0..g.cols.1).contains(&c))
    };
    input_check_where(scan, channels, in_region)
}

/// [`input_check`] over the pixels (row, column) for which `used` is true: the pixels an
/// analysis actually reads (e.g. the parabola windows around a filament's row maxima).
pub fn input_check_where(
    scan: &Scan,
    channels: &[&str],
    used: impl Fn(usize, usize) -> bool,
) -> InputCheck {
    let mut out = InputCheck::default();
    let in_region = |r: usize, c: usize| used(r, c);
    let (rows, cols) = scan.sx.data.dim();
    let n_used = (0..rows)
        .flat_map(|r| (0..cols).map(move |c| (r, c)))
        .filter(|&(r, c)| in_region(r, c))
        .count();
    let range = scan.meta["clipped"]["range"]
        .as_str()
        .map(|r| format!(" (at the {r})"))
        .unwrap_or_default();
    for (k, name) in ["sx", "sy", "sz"].into_iter().enumerate() {
        if !channels.iter().any(|c| c.eq_ignore_ascii_case(name)) {
            continue;
        }
        let n = match &scan.flags.clipped[k] {
            Some(a) => a
                .indexed_iter()
                .filter(|((r, c), &v)| v > 0 && in_region(*r, *c))
                .count(),
            None => scan.meta["clipped"][name]["pixels"].as_u64().unwrap_or(0) as usize,
        };
        out.clipped_pixels[k] = n;
        if n > 0 {
            let (noun, verb) = if n == 1 {
                ("pixel", "is")
            } else {
                ("pixels", "are")
            };
            out.warnings
                .push(format!("{n} {noun} of {} {verb} clipped{range}", LABELS[k]));
            if out.refusal.is_none() {
                out.refusal = all_bad(
                    n,
                    n_used,
                    &format!("of {}", LABELS[k]),
                    &format!("clipped{range}"),
                );
            }
        }
    }
    let dark = match &scan.flags.dark {
        Some(a) => a
            .indexed_iter()
            .filter(|((r, c), &v)| v > 0 && in_region(*r, *c))
            .count(),
        None => scan.meta["dark"]["pixels"].as_u64().unwrap_or(0) as usize,
    };
    out.dark_pixels = dark;
    if dark > 0 {
        let floor = scan.meta["dark"]["floor"]
            .as_str()
            .map(|f| format!(" below {f}"))
            .unwrap_or_default();
        let (noun, verb) = if dark == 1 {
            ("pixel", "is")
        } else {
            ("pixels", "are")
        };
        out.warnings.push(format!(
            "{dark} {noun} {verb} dark (the QPD sum{floor}: laser off or beam blocked?)"
        ));
        if out.refusal.is_none() {
            out.refusal = all_bad(dark, n_used, "", &format!("dark (the QPD sum{floor})"));
        }
    }
    out
}

impl PixelFlags {
    /// The flags of channel `name` (`"sx"`, `"sy"`, `"sz"`) of `scan` and its dark pixels;
    /// `None` when no pixel is clipped or dark.
    pub fn of_channel(scan: &Scan, name: &str) -> Option<PixelFlags> {
        let k = ["sx", "sy", "sz"].iter().position(|c| *c == name)?;
        let dim = scan.sx.data.dim();
        let mut mask = Array2::<u8>::zeros(dim);
        let mut unlocated = [0usize; 2];
        match &scan.flags.clipped[k] {
            Some(a) if a.dim() == dim => {
                mask.zip_mut_with(a, |m, &n| *m |= if n > 0 { CLIPPED } else { 0 })
            }
            _ => unlocated[0] = scan.meta["clipped"][name]["pixels"].as_u64().unwrap_or(0) as usize,
        }
        match &scan.flags.dark {
            Some(a) if a.dim() == dim => {
                mask.zip_mut_with(a, |m, &d| *m |= if d > 0 { DARK } else { 0 })
            }
            _ => unlocated[1] = scan.meta["dark"]["pixels"].as_u64().unwrap_or(0) as usize,
        }
        if mask.iter().all(|&m| m == 0) && unlocated == [0, 0] {
            return None;
        }
        Some(PixelFlags {
            mask,
            channel: LABELS[k].to_string(),
            derived: None,
            range: scan.meta["clipped"]["range"].as_str().map(str::to_string),
            floor: scan.meta["dark"]["floor"].as_str().map(str::to_string),
            unlocated,
        })
    }
}

/// [`input_check_where`] for an image: its clipped and dark pixels (carried from the scan
/// channel it came from, [`PixelFlags`]) among those `used`. An image with no flags is clean.
pub fn image_check(img: &crate::data::Image, used: impl Fn(usize, usize) -> bool) -> InputCheck {
    flags_check(img.flags.as_deref(), used)
}

/// [`image_check`] on the flags themselves (e.g. those of a derivative an analysis computes
/// inside, [`PixelFlags::derived`]).
pub fn flags_check(f: Option<&PixelFlags>, used: impl Fn(usize, usize) -> bool) -> InputCheck {
    let mut out = InputCheck::default();
    let Some(f) = f else {
        return out;
    };
    let (mut n_used, mut clipped, mut dark) = (0, 0, 0);
    for ((r, c), &m) in f.mask.indexed_iter() {
        if !used(r, c) {
            continue;
        }
        n_used += 1;
        clipped += usize::from(m & CLIPPED != 0);
        dark += usize::from(m & DARK != 0);
    }
    clipped += f.unlocated[0];
    dark += f.unlocated[1];
    let range = f
        .range
        .as_ref()
        .map(|r| format!(" (at the {r})"))
        .unwrap_or_default();
    let floor = f
        .floor
        .as_ref()
        .map(|r| format!(" below {r}"))
        .unwrap_or_default();
    let ch = &f.channel;
    if clipped > 0 {
        let (noun, verb) = noun_verb(clipped);
        out.warnings.push(match &f.derived {
            None => format!("{clipped} {noun} of {ch} {verb} clipped{range}"),
            Some(d) => {
                format!("{clipped} {noun} of {d} {verb} computed from clipped {ch} pixels{range}")
            }
        });
        out.refusal = all_bad(
            clipped,
            n_used,
            &format!("of {ch}"),
            &format!("clipped{range}"),
        );
        if let Some(k) = LABELS.iter().position(|l| l == ch) {
            out.clipped_pixels[k] = clipped;
        }
    }
    if dark > 0 {
        let (noun, verb) = noun_verb(dark);
        out.warnings.push(match &f.derived {
            None => format!("{dark} {noun} {verb} dark (the QPD sum{floor}: laser off or beam blocked?)"),
            Some(d) => format!("{dark} {noun} of {d} {verb} computed from dark pixels (the QPD sum{floor}: laser off or beam blocked?)"),
        });
        out.dark_pixels = dark;
        if out.refusal.is_none() {
            out.refusal = all_bad(dark, n_used, "", &format!("dark (the QPD sum{floor})"));
        }
    }
    out
}

fn noun_verb(n: usize) -> (&'static str, &'static str) {
    if n == 1 {
        ("pixel", "is")
    } else {
        ("pixels", "are")
    }
}

/// Samples at or beyond the rail of one pixel: (row, column, [Sx, Sy, Sz] sample counts).
pub type ClippedPixel = (usize, usize, [u32; 3]);

/// A scan's clipped samples per pixel, gathered step by step.
pub struct ClipTally {
    range: Option<InputRange>,
    counts: [Array2<u32>; 3],
}

impl ClipTally {
    /// For a scan of `rows` × `cols` pixels on a QPD of input range `range` (`None`: the QPD
    /// does not know it; nothing is counted or reported).
    pub fn new(rows: usize, cols: usize, range: Option<InputRange>) -> ClipTally {
        ClipTally {
            range,
            counts: [(); 3].map(|_| Array2::zeros((rows, cols))),
        }
    }

    /// Add the clipped samples of a step's pixels.
    pub fn add(&mut self, pixels: &[ClippedPixel]) {
        for &(r, c, k) in pixels {
            for (ch, n) in self.counts.iter_mut().zip(k) {
                if let Some(v) = ch.get_mut([r, c]) {
                    *v = v.saturating_add(n);
                }
            }
        }
    }

    /// Store the counts and the dark pixels in `scan` (`flags`, `meta.clipped`, `meta.dark`)
    /// and tell the operator through `log` when any pixel is clipped or dark.
    pub fn finish(self, scan: &mut Scan, kind: &str, log: &dyn Fn(&str)) {
        let Some(range) = self.range else {
            return;
        };
        let mut flags = InputFlags::default();
        let mut summary = serde_json::Map::new();
        summary.insert("range".into(), json!(range.describe()));
        let mut said = vec![];
        for (k, counts) in self.counts.into_iter().enumerate() {
            let pixels = counts.iter().filter(|&&n| n > 0).count();
            let samples: u64 = counts.iter().map(|&n| u64::from(n)).sum();
            summary.insert(
                LABELS[k].to_lowercase(),
                json!({ "pixels": pixels, "samples": samples }),
            );
            if pixels > 0 {
                said.push(format!("{pixels} of {} {}", LABELS[k], plural(pixels)));
                flags.clipped[k] = Some(counts);
            }
        }
        scan.meta["clipped"] = serde_json::Value::Object(summary);
        if !said.is_empty() {
            log(&format!(
                "WARNING: {kind}: {} at the rail of the QPD's {} (clipped samples in the scan file: clipped_sx, clipped_sy, clipped_sz)",
                said.join(", "),
                range.describe()
            ));
        }
        if let Some(floor) = range.describe_floor() {
            let dark = scan.sz.data.mapv(|v| u8::from(range.is_dark(v)));
            let n = dark.iter().filter(|&&d| d > 0).count();
            scan.meta["dark"] = json!({ "floor": floor, "pixels": n });
            if n > 0 {
                log(&format!(
                    "WARNING: {kind}: {n} dark {} (the sum below {floor}: laser off or beam blocked?)",
                    plural(n)
                ));
                flags.dark = Some(dark);
            }
        }
        scan.flags = flags;
    }
}

fn plural(n: usize) -> &'static str {
    if n == 1 {
        "pixel"
    } else {
        "pixels"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::Image;
    use serde_json::json;

    fn scan(flags: InputFlags, meta: serde_json::Value) -> Scan {
        let img = Image::new(Array2::zeros((2, 3)), vec![0.0, 1.0, 2.0], vec![0.0, 1.0]);
        Scan {
            flags,
            ..Scan::complete([img.clone(), img.clone(), img], meta)
        }
    }

    /// A scan whose Sx has the clipped samples `a` per pixel, read at a ±0.2 V input range.
    fn sx_clipped(a: Array2<u32>) -> Scan {
        let flags = InputFlags {
            clipped: [Some(a), None, None],
            dark: None,
        };
        scan(flags, json!({"clipped": {"range": "±0.2 V input range"}}))
    }

    #[test]
    fn counts_the_channels_and_the_region_asked_about() {
        let mut a = Array2::<u32>::zeros((2, 3));
        a[[0, 0]] = 5;
        a[[1, 2]] = 1;
        let s = sx_clipped(a);
        let c = input_check(&s, &["sx", "sy"], None);
        assert_eq!(c.clipped_pixels, [2, 0, 0]);
        assert_eq!(
            c.warnings,
            vec!["2 pixels of Sx are clipped (at the ±0.2 V input range)"]
        );
        // Sy only: clean; a region holding one of the two pixels
        assert!(input_check(&s, &["sy"], None).is_clean());
        let r = Region {
            rows: (1, 2),
            cols: (0, 3),
        };
        assert_eq!(
            input_check(&s, &["sx"], Some(r)).warnings,
            vec!["1 pixel of Sx is clipped (at the ±0.2 V input range)"]
        );
    }

    #[test]
    fn dark_pixels_and_metadata_only_counts_are_reported() {
        let s = scan(
            InputFlags {
                clipped: [None, None, None],
                dark: Some(Array2::ones((2, 3))),
            },
            json!({"dark": {"floor": "0.1 V on the sum input", "pixels": 6},
                   "clipped": {"sy": {"pixels": 3, "samples": 30}}}),
        );
        let c = input_check(&s, &["sx", "sy"], None);
        assert_eq!((c.clipped_pixels, c.dark_pixels), ([0, 3, 0], 6));
        assert_eq!(
            c.warnings,
            vec![
                "3 pixels of Sy are clipped",
                "6 pixels are dark (the QPD sum below 0.1 V on the sum input: laser off or beam blocked?)"
            ]
        );
    }

    #[test]
    fn every_pixel_used_clipped_or_dark_is_a_refusal_naming_the_condition() {
        let mut a = Array2::<u32>::zeros((2, 3));
        a[[1, 0]] = 3;
        a[[1, 1]] = 3;
        a[[1, 2]] = 3;
        let s = sx_clipped(a);
        // the whole scan: half clipped, a warning
        let c = input_check(&s, &["sx"], None);
        assert_eq!(c.refusal, None);
        assert_eq!(c.clone().gate("fit").unwrap(), c.warnings);
        // the clipped row only: every pixel used at the rail
        let r = Region {
            rows: (1, 2),
            cols: (0, 3),
        };
        assert_eq!(
            input_check(&s, &["sx"], Some(r)).gate("fit").unwrap_err(),
            "fit: every pixel it uses (3 of Sx) is clipped (at the ±0.2 V input range): the answer would be meaningless; lower the signal or raise the QPD's input range"
        );
        let dark = scan(
            InputFlags {
                clipped: [None, None, None],
                dark: Some(Array2::ones((2, 3))),
            },
            json!({"dark": {"floor": "0.1 V on the sum input", "pixels": 6}}),
        );
        assert_eq!(
            input_check(&dark, &["sx"], None).refusal.unwrap(),
            "every pixel it uses (6) is dark (the QPD sum below 0.1 V on the sum input): the answer would be meaningless; check the laser and the beam path"
        );
    }

    #[test]
    fn an_image_carries_its_channels_flags_through_a_derivative_and_arithmetic() {
        let mut a = Array2::<u32>::zeros((3, 5));
        a[[1, 2]] = 7;
        let s = scan3x5(InputFlags {
            clipped: [Some(a), None, None],
            dark: None,
        });
        let f = PixelFlags::of_channel(&s, "sx").unwrap();
        assert!(PixelFlags::of_channel(&s, "sy").is_none(), "Sy is clean");
        let mut img = s.sx.clone();
        img.flags = Some(std::sync::Arc::new(f.clone()));
        assert_eq!(
            image_check(&img, |_, _| true).warnings,
            vec!["1 pixel of Sx is clipped (at the ±1 input range (signal units))"]
        );
        // a central difference along x reaches one column either side: three pixels
        let d = f.derived("the sensitivity ∂/∂x", 1, 0);
        let flagged: Vec<(usize, usize)> = d
            .mask
            .indexed_iter()
            .filter(|(_, &m)| m != 0)
            .map(|(i, _)| i)
            .collect();
        assert_eq!(flagged, vec![(1, 1), (1, 2), (1, 3)]);
        let c = flags_check(Some(&d), |r, _| r == 1);
        assert_eq!(
            c.warnings,
            vec!["3 pixels of the sensitivity ∂/∂x are computed from clipped Sx pixels (at the ±1 input range (signal units))"]
        );
        assert!(c.refusal.is_none(), "3 of the 5 pixels of row 1");
        // pixels away from it are clean; a window of the three flagged ones is refused
        assert!(flags_check(Some(&d), |r, _| r != 1).is_clean());
        assert!(flags_check(Some(&d), |r, c| r == 1 && (1..4).contains(&c))
            .refusal
            .is_some());
        // a crop keeps the flags it holds, and none when it holds none
        assert_eq!(f.crop((1, 2), (2, 4)).unwrap().mask.sum(), CLIPPED);
        assert!(f.crop((0, 0), (0, 4)).is_none());
        // Sx + a dark Sy image: both conditions, both channels named
        let mut g = f.clone();
        g.channel = "Sy".into();
        g.mask.fill(0);
        g.mask[[0, 0]] = DARK;
        let u = f.union(&g);
        assert_eq!(u.channel, "Sx, Sy");
        assert_eq!((u.mask[[1, 2]], u.mask[[0, 0]]), (CLIPPED, DARK));
    }

    fn scan3x5(flags: InputFlags) -> Scan {
        let img = Image::new(
            Array2::zeros((3, 5)),
            vec![0.0, 0.1, 0.2, 0.3, 0.4],
            vec![0.0, 0.1, 0.2],
        );
        let meta = json!({"clipped": {"range": "±1 input range (signal units)"}});
        Scan {
            flags,
            ..Scan::complete([img.clone(), img.clone(), img], meta)
        }
    }

    #[test]
    fn the_rail_and_the_top_code_count_as_clipped() {
        let r = InputRange::new(0.2, "V");
        assert!(r.at_rail(0.2) && r.at_rail(-0.2) && r.at_rail(0.25));
        // a 14-bit converter's top code, 8191/8192 of full scale
        assert!(r.at_rail(0.2 * 8191.0 / 8192.0));
        // three codes under full scale is a measurement
        assert!(!r.at_rail(0.2 * 8189.0 / 8192.0));
        assert!(r.at_rail(f64::NAN) && r.at_rail(f64::INFINITY));
        assert_eq!(r.describe(), "±0.2 V input range");
    }

    #[test]
    fn dark_compares_the_sum_input_through_the_calibration() {
        // sz = −2 · (input − 1): input = sz / −2 + 1; floor 0.5 V
        let r = InputRange::new(10.0, "V").with_sum(Some(0.5), -2.0, 1.0);
        assert!(r.is_dark(1.2)); // input 0.4 V
        assert!(!r.is_dark(0.8)); // input 0.6 V
        assert!(!r.is_dark(f64::NAN));
        assert_eq!(r.describe_floor().unwrap(), "0.5 V on the sum input");
        assert!(!InputRange::new(1.0, "V").is_dark(-100.0));
    }
}
