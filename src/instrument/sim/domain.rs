//! The point dipole's domain check: an explicit, bounded stage of the render pipeline.
//!
//! For every bead that can be off (the suspect rule below), the check asks the focused-beam Mie
//! tier how far the point dipole's normalised sensitivity is off
//! ([`mie_beam::point_dipole_error`], about 0.1 s per new (optics, d, n) in a release build).
//! The renderer reads the result: model notes in the paraxial beam, automatic Mie spheres in
//! the vector beam. Results are remembered in a [`DomainMemo`] the caller owns
//! (the simulator keeps one per session), bounded to [`DomainMemo::CAPACITY`] entries.

use crate::optics::mie_beam;
use crate::optics::params::{OpticsError, REF_BEAD_D_NM, REF_BEAD_N};
use crate::optics::ValidOptics;
use std::collections::VecDeque;
use std::time::Instant;

use super::scene::Scene;

/// Point-dipole error beyond which the simulator says so (the model knob's 1 % criterion,
/// docs/accuracy.md#model_500).
pub const MODEL_NOTE_TOLERANCE: f64 = 0.01;

/// Only beads that can be off are checked, to keep ordinary scenes free: d ≥ 150 nm, or
/// d ≥ 20 nm with an index more than 0.03 from polystyrene's. The gates come from the point
/// dipole's error against the Mie tier in the default vector beam
/// ([`mie_beam::point_dipole_error`], 10 nm steps): polystyrene crosses 1 % between 190 and
/// 200 nm (n = 1.542: 0.68 % at 150 nm), silica (1.45) between 100 and 110 nm, n = 1.35
/// between 60 and 150 nm, n = 2 between 50 and 60 nm, n = 4 and 5 between 20 and 30 nm
/// (at 20 nm: −0.60 %, −0.81 %). Below 20 nm every index of the scene's range (1–5) is within
/// 1 %; the unit test `the_suspect_gates_leave_no_bead_off_by_1_percent_unchecked` holds the
/// gates' edges to it.
pub fn is_suspect(d_nm: f64, n: f64) -> bool {
    d_nm >= 150.0 || (d_nm >= 20.0 && (n - REF_BEAD_N).abs() > 0.03)
}

/// Remembered point-dipole errors, keyed by (optics, d, n); oldest dropped first beyond
/// [`Self::CAPACITY`]. The reference bead's Mie sensitivity (the error's denominator) is
/// remembered per optics apart, so a new species costs one Mie response, not two.
#[derive(Debug, Default, Clone)]
pub struct DomainMemo {
    entries: VecDeque<(ValidOptics, u64, u64, Result<f64, OpticsError>)>,
    /// (optics, the 110 nm polystyrene bead's M/α), the most recent [`Self::REF_CAPACITY`]
    refs: VecDeque<(ValidOptics, Result<f64, OpticsError>)>,
}

/// The memo [`DomainCheck::run_shared`] uses: one per process, so that scenes rendered again
/// and again (`simulate`, `Renderer::checked`) pay the Mie tier once per bead species.
static SHARED: std::sync::Mutex<DomainMemo> = std::sync::Mutex::new(DomainMemo {
    entries: VecDeque::new(),
    refs: VecDeque::new(),
});

impl DomainMemo {
    /// Most (optics, d, n) results kept (a result is 24 bytes plus the optics, ~200 B).
    pub const CAPACITY: usize = 64;
    /// Most reference-bead results kept (one per optics).
    pub const REF_CAPACITY: usize = 8;

    /// The point dipole's error for (d_nm nm, n) under `optics`, computed once per memo entry:
    /// [`mie_beam::point_dipole_error`]'s value, from its two factors.
    pub fn error(&mut self, optics: &ValidOptics, d_nm: f64, n: f64) -> Result<f64, OpticsError> {
        if let Some(e) = self.remembered(optics, d_nm, n) {
            return e.clone();
        }
        let key = (d_nm.to_bits(), n.to_bits());
        let e = self
            .reference(optics)
            .and_then(|r| Ok(r / mie_beam::max_sensitivity_per_alpha(optics, d_nm, n)? - 1.0));
        if self.entries.len() == Self::CAPACITY {
            self.entries.pop_front();
        }
        self.entries
            .push_back((optics.clone(), key.0, key.1, e.clone()));
        e
    }

    /// The remembered result for (optics, d_nm, n), if any.
    fn remembered(
        &self,
        optics: &ValidOptics,
        d_nm: f64,
        n: f64,
    ) -> Option<&Result<f64, OpticsError>> {
        let key = (d_nm.to_bits(), n.to_bits());
        self.entries
            .iter()
            .find(|(o, d, nn, _)| (*d, *nn) == key && o == optics)
            .map(|e| &e.3)
    }

    /// The reference bead's M/α under `optics` (remembered).
    fn reference(&mut self, optics: &ValidOptics) -> Result<f64, OpticsError> {
        if let Some((_, r)) = self.refs.iter().find(|(o, _)| o == optics) {
            return r.clone();
        }
        let r = mie_beam::max_sensitivity_per_alpha(optics, REF_BEAD_D_NM, REF_BEAD_N);
        if self.refs.len() == Self::REF_CAPACITY {
            self.refs.pop_front();
        }
        self.refs.push_back((optics.clone(), r.clone()));
        r
    }

    /// Compute the species of `species` not yet remembered (and the reference) in parallel,
    /// one Mie response each, and remember them: a scene's first check costs the slowest
    /// response per core, not their sum. Same values as [`Self::error`] one by one.
    pub fn fill(&mut self, optics: &ValidOptics, species: &[(f64, f64)]) {
        use rayon::prelude::*;
        let mut todo: Vec<(f64, f64)> = vec![];
        for &(d, n) in species {
            if self.remembered(optics, d, n).is_none() && !todo.contains(&(d, n)) {
                todo.push((d, n));
            }
        }
        let need_ref = !self.refs.iter().any(|(o, _)| o == optics);
        if todo.is_empty() {
            return;
        }
        let n_species = todo.len();
        if need_ref {
            todo.push((REF_BEAD_D_NM, REF_BEAD_N));
        }
        let m: Vec<Result<f64, OpticsError>> = todo
            .par_iter()
            .map(|&(d, n)| mie_beam::max_sensitivity_per_alpha(optics, d, n))
            .collect();
        let mut m = m.into_iter();
        let per_alpha: Vec<_> = m.by_ref().take(n_species).collect();
        if need_ref {
            let r = m.next().expect("the reference was computed");
            if self.refs.len() == Self::REF_CAPACITY {
                self.refs.pop_front();
            }
            self.refs.push_back((optics.clone(), r));
        }
        let reference = self.reference(optics);
        for ((d, n), pa) in todo.iter().zip(per_alpha) {
            let e = reference.clone().and_then(|r| Ok(r / pa? - 1.0));
            if self.entries.len() == Self::CAPACITY {
                self.entries.pop_front();
            }
            self.entries
                .push_back((optics.clone(), d.to_bits(), n.to_bits(), e));
        }
    }

    /// Remember what `other` remembers and `self` does not (newest last, bounded as always).
    fn merge(&mut self, other: &DomainMemo) {
        for (o, d, n, e) in &other.entries {
            let known = self
                .entries
                .iter()
                .any(|(oo, dd, nn, _)| (dd, nn) == (d, n) && oo == o);
            if !known {
                if self.entries.len() == Self::CAPACITY {
                    self.entries.pop_front();
                }
                self.entries.push_back((o.clone(), *d, *n, e.clone()));
            }
        }
        for (o, r) in &other.refs {
            if !self.refs.iter().any(|(oo, _)| oo == o) {
                if self.refs.len() == Self::REF_CAPACITY {
                    self.refs.pop_front();
                }
                self.refs.push_back((o.clone(), r.clone()));
            }
        }
    }

    /// Number of remembered results.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// True when nothing is remembered.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

/// The suspect bead species of `scene` ([`is_suspect`]), each once, in order of first
/// appearance; none when the scene pins a tier by naming `mie` or `finite_size`.
fn suspects(scene: &Scene) -> Vec<(f64, f64)> {
    let pinned = scene.effects.mie.is_some() || scene.effects.finite_size.is_some();
    let mut species: Vec<(f64, f64)> = vec![];
    for b in scene.beads.iter().filter(|_| !pinned) {
        let (d, n) = (b.d_nm, b.n);
        if is_suspect(d, n) && !species.contains(&(d, n)) {
            species.push((d, n));
        }
    }
    species
}

/// One suspect bead species of a scene and how far the point dipole is off for it
/// (relative error, dimensionless; `None` when the Mie tier could not say, e.g. n = medium).
#[derive(Debug, Clone, PartialEq)]
pub struct DomainEntry {
    pub d_nm: f64,
    pub n: f64,
    pub error: Option<f64>,
}

/// The result of the domain check for one (optics, scene).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DomainCheck {
    /// Suspect species, in order of first appearance, each once.
    pub entries: Vec<DomainEntry>,
    /// Wall time the check took (s), shown as the render stage `domain check`.
    pub seconds: f64,
}

impl DomainCheck {
    /// Check every suspect bead species of `scene` (see [`is_suspect`]), through `memo`.
    /// Nothing to check when the scene pins a tier by naming `mie` or `finite_size`: the
    /// renderer then neither notes nor switches models.
    pub fn run(optics: &ValidOptics, scene: &Scene, memo: &mut DomainMemo) -> DomainCheck {
        Self::of_species(optics, suspects(scene), memo, Instant::now())
    }

    fn of_species(
        optics: &ValidOptics,
        species: Vec<(f64, f64)>,
        memo: &mut DomainMemo,
        t: Instant,
    ) -> DomainCheck {
        memo.fill(optics, &species);
        let entries = species
            .into_iter()
            .map(|(d, n)| DomainEntry {
                d_nm: d,
                n,
                error: memo.error(optics, d, n).ok(),
            })
            .collect();
        DomainCheck {
            entries,
            seconds: t.elapsed().as_secs_f64(),
        }
    }

    /// [`DomainCheck::run`] through the process-wide memo (bounded like any memo): what
    /// [`super::Renderer::checked`] and so `simulate` use.
    ///
    /// The shared memo is locked to read what it remembers, or to copy it and merge what this
    /// check computed, never while Mie responses are computed: they run on rayon's pool, and a caller outside it
    /// that held the lock while waiting for the pool deadlocked with pool threads waiting for
    /// the lock (a truth-sweep replay beside a running sweep, 2026-12-06).
    pub fn run_shared(optics: &ValidOptics, scene: &Scene) -> DomainCheck {
        let lock = || {
            SHARED
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
        };
        let t = Instant::now();
        let species = suspects(scene);
        {
            // everything remembered (the usual case, and every scene without a suspect bead):
            // nothing to compute, so the lock may be held
            let mut memo = lock();
            if species
                .iter()
                .all(|&(d, n)| memo.remembered(optics, d, n).is_some())
            {
                return Self::of_species(optics, species, &mut memo, t);
            }
        }
        let mut local = lock().clone();
        let check = Self::of_species(optics, species, &mut local, t);
        lock().merge(&local);
        check
    }

    /// The point dipole's error for bead (d, n) when it is beyond [`MODEL_NOTE_TOLERANCE`].
    pub fn outside(&self, d_nm: f64, n: f64) -> Option<f64> {
        self.entries
            .iter()
            .find(|e| (e.d_nm, e.n) == (d_nm, n))
            .and_then(|e| e.error)
            .filter(|e| e.abs() > MODEL_NOTE_TOLERANCE)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memo_is_bounded_and_remembers() {
        let o = ValidOptics::default();
        let mut m = DomainMemo::default();
        // n = medium index: the check errors fast (α = 0), which is enough to fill the memo.
        for i in 0..(DomainMemo::CAPACITY + 5) {
            let _ = m.error(&o, 100.0 + i as f64, o.n_medium);
        }
        assert_eq!(m.len(), DomainMemo::CAPACITY);
    }

    /// The memo's error, from the two remembered factors, is exactly the optics function's.
    #[test]
    fn memo_error_equals_point_dipole_error() {
        let o = ValidOptics::default();
        let mut m = DomainMemo::default();
        let want = mie_beam::point_dipole_error(&o, 250.0, 1.572).unwrap();
        assert!(want.abs() > 1e-3, "{want}");
        assert_eq!(m.error(&o, 250.0, 1.572).unwrap(), want);
        assert_eq!(m.refs.len(), 1);
        assert_eq!(m.error(&o, 250.0, 1.572).unwrap(), want);
    }

    #[test]
    fn parallel_fill_remembers_the_same_errors_once_each() {
        let o = ValidOptics::default();
        let species = [(250.0, 1.572), (60.0, 1.45), (250.0, 1.572)];
        let mut a = DomainMemo::default();
        a.fill(&o, &species);
        assert_eq!((a.len(), a.refs.len()), (2, 1));
        let mut b = DomainMemo::default();
        for (d, n) in species {
            assert_eq!(a.error(&o, d, n), b.error(&o, d, n));
        }
        assert_eq!(a.len(), 2, "nothing computed again");
        a.fill(&o, &species);
        assert_eq!(a.len(), 2);
    }

    #[test]
    fn suspect_rule() {
        assert!(!is_suspect(110.0, REF_BEAD_N));
        assert!(is_suspect(200.0, REF_BEAD_N));
        assert!(is_suspect(60.0, 1.45));
        assert!(!is_suspect(149.0, REF_BEAD_N + 0.02));
        assert!(is_suspect(150.0, REF_BEAD_N));
        assert!(is_suspect(20.0, 1.45) && !is_suspect(19.9, 5.0));
    }

    #[test]
    fn the_suspect_gates_leave_no_bead_off_by_1_percent_unchecked() {
        // just inside the gates, where the point dipole's error is largest for beads left
        // unchecked (it grows with d, and with |n − n_medium|, over these ranges): polystyrene-like
        // indices up to 149 nm, any index of the scene's range (1–5) below 20 nm
        let o = ValidOptics::default();
        for (d, n) in [
            (149.0, REF_BEAD_N - 0.0299),
            (149.0, REF_BEAD_N),
            (149.0, REF_BEAD_N + 0.0299),
            (19.9, 5.0),
            (19.9, 1.0),
        ] {
            assert!(!is_suspect(d, n));
            let e = mie_beam::point_dipole_error(&o, d, n).unwrap();
            assert!(e.abs() < MODEL_NOTE_TOLERANCE, "d {d} nm, n {n}: {e}");
        }
        // and the gates are not wider than they need be: just outside, a bead is off by more
        // than 1 % (polystyrene at 200 nm, n = 5 at 30 nm)
        for (d, n) in [(200.0, REF_BEAD_N), (30.0, 5.0)] {
            let e = mie_beam::point_dipole_error(&o, d, n).unwrap();
            assert!(e.abs() > MODEL_NOTE_TOLERANCE, "d {d} nm, n {n}: {e}");
        }
    }
}
