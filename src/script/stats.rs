//! Binding family `stats`: summaries, histograms and straight-line fits of numbers.

use super::analysis_values::to_map;
use super::registry::{binding_list, err, fail, numbers, Doc, RResult, Registrar};
use super::types::floats;
use crate::analysis::stats::{histogram, linfit, loglog_fit, summary, MAX_BINS};
use rhai::{Array, Dynamic, Map};

binding_list! { pub fn register { bind_summary, bind_histogram, bind_line_fits } }

/// `summary(values)`.
fn bind_summary(r: &mut Registrar) {
    let d = Doc::func("summary")
        .arg(
            "values",
            "array",
            "",
            "numbers (non-finite values are skipped and counted)",
        )
        .returns("map", "#{n, n_skipped, mean, std, sem, min, max}")
        .summary("mean, sample std, standard error, min, max")
        .example("summary([1.0, 2.0, 3.0]).std", "1.0")
        .example("summary([])", "error: ");
    r.bind(d, |a: Array| summary_of(a));
}

/// `histogram(values, bins, [range])`.
fn bind_histogram(r: &mut Registrar) {
    let d = Doc::func("histogram")
        .arg("values", "array", "", "numbers")
        .arg(
            "bins",
            "int",
            "",
            &format!("number of bins, 1 ≤ bins ≤ {MAX_BINS}"),
        )
        .opt(
            "range",
            "array",
            "",
            "[lo, hi] (default: min and max of the values)",
        )
        .returns(
            "map",
            "#{edges, counts, centres, n_outside, n_skipped, all_equal}",
        )
        .summary("histogram with equal bins")
        .example("histogram([1.0, 2.0, 2.5, 4.0], 3).counts", "[1, 2, 1]")
        .example("histogram([1.0], 0)", "error: bins = 0");
    r.bind(d, |a: Array, bins: i64| histogram_of(a, bins, None));
    r.overload("histogram", |a: Array, bins: i64, range: Array| {
        histogram_of(a, bins, Some(range))
    });
}

/// `linfit`, `loglog_fit`: straight lines with uncertainties.
fn bind_line_fits(r: &mut Registrar) {
    for (name, log) in [("linfit", false), ("loglog_fit", true)] {
        let d = Doc::func(name)
            .arg("x", "array", "", "abscissae")
            .arg("y", "array", "", "ordinates")
            .opt("sigma_y", "array", "", "1σ of each y (weighted fit)")
            .returns("map", "#{slope, intercept, slope_err, intercept_err, cov, chi2, r2, n}")
            .summary(if log {
                "straight line through (ln x, ln y): y = e^intercept · x^slope (e.g. the d^3.02±0.04 fit of Fig. 3c)"
            } else {
                "least-squares straight line y = intercept + slope·x with uncertainties"
            })
            .example(
                &format!("{name}([1.0, 2.0, 4.0], [{}]).slope", if log { "2.0, 16.0, 128.0" } else { "1.0, 3.0, 7.0" }),
                if log { "3.0" } else { "2.0" },
            )
            .example(&format!("{name}([1.0, 1.0], [1.0, 2.0])"), "error: ");
        r.bind(d, move |x: Array, y: Array| line_fit(name, log, x, y, None));
        r.overload(name, move |x: Array, y: Array, s: Array| {
            line_fit(name, log, x, y, Some(s))
        });
    }
}

/// `summary(values)`: count, mean, sample standard deviation, standard error, min and max of
/// the finite values (the others are skipped and counted).
fn summary_of(a: Array) -> RResult<Map> {
    let v = numbers("summary", "values", &Dynamic::from_array(a))?;
    let s = summary(&v).map_err(|e| err("summary", e))?;
    Ok(to_map(&s))
}

/// `histogram(values, bins[, range])`: counts in `bins` equal bins over `range` = [lo, hi]
/// (default: min and max of the values), with edges and centres.
fn histogram_of(a: Array, bins: i64, range: Option<Array>) -> RResult<Map> {
    let range = match range {
        None => None,
        Some(rg) => {
            let v = numbers("histogram", "range", &Dynamic::from_array(rg))?;
            if v.len() != 2 {
                return fail("histogram: range must be [lo, hi]");
            }
            Some((v[0], v[1]))
        }
    };
    if !(1..=MAX_BINS as i64).contains(&bins) {
        return fail(format!(
            "histogram: bins = {bins} is out of range: 1 ≤ bins ≤ {MAX_BINS}"
        ));
    }
    let v = numbers("histogram", "values", &Dynamic::from_array(a))?;
    let h = histogram(&v, bins as usize, range).map_err(|e| err("histogram", e))?;
    let mut m = to_map(&h);
    m.insert("centres".into(), floats(&h.centres()).into());
    Ok(m)
}

/// `linfit(x, y[, sigma_y])` (`log` false): least-squares line y = intercept + slope·x;
/// `loglog_fit` (`log` true): the same through (ln x, ln y). Weighted by 1/sigma_y² when given.
fn line_fit(name: &str, log: bool, x: Array, y: Array, sigma_y: Option<Array>) -> RResult<Map> {
    let x = numbers(name, "x", &Dynamic::from_array(x))?;
    let y = numbers(name, "y", &Dynamic::from_array(y))?;
    let s = sigma_y
        .map(|s| numbers(name, "sigma_y", &Dynamic::from_array(s)))
        .transpose()?;
    if x.len() != y.len() || s.as_ref().is_some_and(|s| s.len() != x.len()) {
        return fail(format!(
            "{name}: x, y (and sigma_y) must have the same length, got {} and {}",
            x.len(),
            y.len()
        ));
    }
    let r = if log {
        loglog_fit(&x, &y, s.as_deref())
    } else {
        linfit(&x, &y, s.as_deref())
    }
    .map_err(|e| err(name, e))?;
    Ok(to_map(&r))
}
