//! What the QPD sees: bfpscope's simulator (`instrument::sim::Renderer`, the ideal,
//! noise-free signal as `bfpscope emulate qpd` serves it) of a scene at the stage's position,
//! turned into the volts of the QPD amplifier.
//!
//! The scene point under the focus is `stage position − origin` (µm), the convention of the
//! emulators (`sim_signal_source`: the stage position is the scene coordinate). Default scene:
//! the paper's reference bead (110 nm polystyrene) at the origin; `FAKEBENCH_SCENE` names a
//! scene file (the JSON of `bfpscope emulate --scene`).
//!
//! A stream samples the signal at up to 800 kS/s per channel at positions that change from
//! sample to sample, so the signal is interpolated (bilinear in x, y; linear in z) on a grid
//! of nodes 5 nm apart, computed tile by tile (32 × 32 nodes per renderer call) when first
//! needed. The interpolation error is of order (5 nm / feature size)² of the signal, below
//! 1e-3 of the peak for a 110 nm bead's ~300 nm wide response.

use crate::config::Config;
use bfpscope::instrument::sim::{Renderer, Scene};
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};

/// Node spacing, µm.
pub const NODE_UM: f64 = 0.005;
const TILE: usize = 32;
const TILES_CAP: usize = 512;

type Tile = Arc<[Vec<f64>; 3]>;

/// The QPD's signal source.
pub struct Qpd {
    scene_path: Option<PathBuf>,
    origin: [f64; 3],
    renderer: Option<Result<Arc<Renderer>, String>>,
    tiles: HashMap<(i64, i64, i64), Tile>,
    /// The tile of the last node looked up: a stream's consecutive samples are nodes of one
    /// tile (a hash lookup per node cost most of a sample's time).
    last: Option<((i64, i64, i64), Tile)>,
}

impl Qpd {
    pub fn new(cfg: &Config) -> Self {
        Qpd {
            scene_path: cfg.scene.clone(),
            origin: cfg.origin(),
            renderer: None,
            tiles: HashMap::new(),
            last: None,
        }
    }

    /// The renderer of the configured scene (built on first use, and kept for the process:
    /// a bench reset does not build it again), or why it cannot be built (printed once).
    pub fn renderer(&mut self) -> Result<Arc<Renderer>, String> {
        type Cache = Mutex<HashMap<Option<PathBuf>, Result<Arc<Renderer>, String>>>;
        static BUILT: OnceLock<Cache> = OnceLock::new();
        if self.renderer.is_none() {
            let cache = BUILT.get_or_init(Default::default);
            let mut g = cache.lock().unwrap_or_else(|e| e.into_inner());
            let r = g
                .entry(self.scene_path.clone())
                .or_insert_with(|| {
                    let r = build_renderer(self.scene_path.as_deref());
                    if let Err(e) = &r {
                        eprintln!("fakebench: {e}; the QPD inputs read 0 V signal");
                    }
                    r
                })
                .clone();
            self.renderer = Some(r);
        }
        self.renderer.clone().expect("set above")
    }

    fn tile(&mut self, key: (i64, i64, i64)) -> Tile {
        if let Some(t) = self.tiles.get(&key) {
            return t.clone();
        }
        let xs: Vec<f64> = (0..TILE)
            .map(|i| (key.0 * TILE as i64 + i as i64) as f64 * NODE_UM)
            .collect();
        let ys: Vec<f64> = (0..TILE)
            .map(|i| (key.1 * TILE as i64 + i as i64) as f64 * NODE_UM)
            .collect();
        let z = key.2 as f64 * NODE_UM;
        let planes = match self.renderer() {
            Ok(r) => r.render_grid_ideal(&xs, &ys, z),
            Err(_) => [
                vec![0.0; TILE * TILE],
                vec![0.0; TILE * TILE],
                vec![0.0; TILE * TILE],
            ],
        };
        if self.tiles.len() >= TILES_CAP {
            self.tiles.clear();
        }
        let t: Tile = Arc::new(planes);
        self.tiles.insert(key, t.clone());
        t
    }

    fn node(&mut self, ix: i64, iy: i64, iz: i64) -> [f64; 3] {
        let t = TILE as i64;
        let key = (ix.div_euclid(t), iy.div_euclid(t), iz);
        let k = (iy.rem_euclid(t) * t + ix.rem_euclid(t)) as usize;
        if let Some((lk, tile)) = &self.last {
            if *lk == key {
                return [tile[0][k], tile[1][k], tile[2][k]];
            }
        }
        let tile = self.tile(key);
        let v = [tile[0][k], tile[1][k], tile[2][k]];
        self.last = Some((key, tile));
        v
    }

    /// (Sx, Sy, Sz) in signal units with the stage at `stage` (µm).
    pub fn signal(&mut self, stage: [f64; 3]) -> [f64; 3] {
        let p = [
            (stage[0] - self.origin[0]) / NODE_UM,
            (stage[1] - self.origin[1]) / NODE_UM,
            (stage[2] - self.origin[2]) / NODE_UM,
        ];
        let (fx, fy, fz) = (p[0].floor(), p[1].floor(), p[2].floor());
        let (u, v, w) = (p[0] - fx, p[1] - fy, p[2] - fz);
        let (ix, iy, iz) = (fx as i64, fy as i64, fz as i64);
        let mut out = [0.0; 3];
        for (dz, wz) in [(0, 1.0 - w), (1, w)] {
            if wz == 0.0 {
                continue;
            }
            for (dy, wy) in [(0, 1.0 - v), (1, v)] {
                for (dx, wx) in [(0, 1.0 - u), (1, u)] {
                    let f = wx * wy * wz;
                    if f == 0.0 {
                        continue;
                    }
                    let n = self.node(ix + dx, iy + dy, iz + dz);
                    for c in 0..3 {
                        out[c] += f * n[c];
                    }
                }
            }
        }
        out
    }
}

fn build_renderer(path: Option<&std::path::Path>) -> Result<Arc<Renderer>, String> {
    let scene = match path {
        None => bfpscope::script::motion::reference_bead_scene(),
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .map_err(|e| format!("FAKEBENCH_SCENE {}: {e}", p.display()))?;
            serde_json::from_str::<Scene>(&text)
                .map_err(|e| format!("FAKEBENCH_SCENE {}: {e}", p.display()))?
        }
    };
    let optics = bfpscope::optics::Optics::default();
    Renderer::checked(
        &optics,
        &scene,
        bfpscope::optics::template::TemplateSpec::default(),
    )
    .map(Arc::new)
    .map_err(|e| format!("FAKEBENCH_SCENE: {e}"))
}
