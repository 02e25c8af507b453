//! `Image`: a 2-D array with physical axes, and `Profile`: a 1-D curve.
//!
//! Convention: `data[[row, col]]`; columns run along the horizontal axis (`x` values, µm),
//! rows along the vertical axis (`y` values, µm; `z` for XZ/YZ scans). Axis values are the
//! pixel centres, strictly monotonic.

use ndarray::Array2;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Pixel values, shape (rows, cols).
    pub data: Array2<f64>,
    /// Horizontal axis (one value per column), µm.
    pub x: Vec<f64>,
    /// Vertical axis (one value per row), µm.
    pub y: Vec<f64>,
    /// Names of the horizontal and vertical axes (`"x"`, `"y"`, `"z"`).
    pub x_name: String,
    pub y_name: String,
}

impl Image {
    /// Build an image; panics only on a programming error (axis lengths not matching the data),
    /// never on user input (callers validate first).
    pub fn new(data: Array2<f64>, x: Vec<f64>, y: Vec<f64>) -> Self {
        assert_eq!(
            data.ncols(),
            x.len(),
            "x axis length must equal the number of columns"
        );
        assert_eq!(
            data.nrows(),
            y.len(),
            "y axis length must equal the number of rows"
        );
        Self {
            data,
            x,
            y,
            x_name: "x".into(),
            y_name: "y".into(),
        }
    }

    pub fn with_axis_names(mut self, x_name: &str, y_name: &str) -> Self {
        self.x_name = x_name.into();
        self.y_name = y_name.into();
        self
    }

    pub fn rows(&self) -> usize {
        self.data.nrows()
    }
    pub fn cols(&self) -> usize {
        self.data.ncols()
    }
    /// Pixel spacing along x (µm); 0 for a single column.
    pub fn dx(&self) -> f64 {
        axis_step(&self.x)
    }
    /// Pixel spacing along y (µm); 0 for a single row.
    pub fn dy(&self) -> f64 {
        axis_step(&self.y)
    }
}

/// Mean spacing of a monotonic axis (0 if it has fewer than two points).
pub fn axis_step(a: &[f64]) -> f64 {
    if a.len() < 2 {
        0.0
    } else {
        (a[a.len() - 1] - a[0]) / (a.len() - 1) as f64
    }
}

/// A 1-D curve: values `v` sampled at positions `t` (µm unless stated).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Profile {
    pub t: Vec<f64>,
    pub v: Vec<f64>,
    /// What `t` measures (e.g. `"x"`, `"arc length"`).
    pub t_name: String,
}

impl Profile {
    pub fn new(t: Vec<f64>, v: Vec<f64>) -> Self {
        assert_eq!(t.len(), v.len());
        Self {
            t,
            v,
            t_name: "x".into(),
        }
    }
}
