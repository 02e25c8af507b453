//! The option keys that several binding families take with one name, type, unit and meaning,
//! each declared once (`Opt`); a key only one family takes stays in that family's file.

use super::doc::Opt;

/// An axis name, `"x"`, `"y"` or `"z"`.
pub const AXIS: Opt = Opt::new("axis", "string", "");
/// A sphere's, filament's or reference bead's diameter.
pub const D_NM: Opt = Opt::new("d_nm", "float", "nm");
pub const DENSITY_G_CM3: Opt = Opt::new("density_g_cm3", "float", "g/cm³");
/// A reference bead's or an object's density.
pub const DENSITY: Opt = Opt::new("density", "float", "g/cm³");
pub const DETECT_SNR: Opt = Opt::new("detect_snr", "float", "");
/// Dwell per point or pixel.
pub const DWELL: Opt = Opt::new("dwell", "float", "s");
/// A refractive index (of a sphere, a filament, the reference bead).
pub const N: Opt = Opt::new("n", "float", "");
pub const PATIENCE: Opt = Opt::new("patience", "int", "");
/// A filament's vertices.
pub const POINTS: Opt = Opt::new("points", "array", "µm");
pub const POLARIZATION: Opt = Opt::new("polarization", "bool", "");
/// Pixel noise.
pub const SIGMA: Opt = Opt::new("sigma", "float", "");
/// Spacing of a bead-model filament's sections.
pub const SPACING_NM: Opt = Opt::new("spacing_nm", "float", "nm");
pub const STENCIL: Opt = Opt::new("stencil", "string", "");
/// A weight in reference-bead units.
pub const WEIGHT: Opt = Opt::new("weight", "float", "");
/// Positions (stage or scene coordinates).
pub const X: Opt = Opt::new("x", "float", "µm");
pub const Y: Opt = Opt::new("y", "float", "µm");
pub const Z: Opt = Opt::new("z", "float", "µm");
