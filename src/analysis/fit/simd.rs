//! The two passes of the separable window sampler ([`FitData::sample_window`](super::problem::FitData::sample_window)), each as portable
//! scalar code and as AVX2 intrinsics with the same operations in the same order per lane (no
//! fused multiply–add), so both give the same bits.

/// One window row's v pass: `vrow[k]` = Σ_b (w_b·T_b[k], d_b·T_b[k]) over the four template
/// rows `taps` (nodes [Sx, Sy]), as [Σw·Sx, Σw·Sy, Σd·Sx, Σd·Sy].
#[inline(always)]
pub(super) fn v_pass(vrow: &mut [[f64; 4]], taps: [&[[f64; 2]]; 4], w: &[f64; 4], d: &[f64; 4]) {
    for (k, acc) in vrow.iter_mut().enumerate() {
        let mut a = [0.0f64; 4];
        for b in 0..4 {
            let n = taps[b][k];
            a[0] += w[b] * n[0];
            a[1] += w[b] * n[1];
            a[2] += d[b] * n[0];
            a[3] += d[b] * n[1];
        }
        *acc = a;
    }
}

/// One window row's u pass: per column, its four taps of `vrow` from `off` weighted by the
/// Keys weights w (values, ∂/∂v) and their derivatives d (∂/∂u), scaled by 1/h for the
/// derivatives and by the channel's mask (0 or 1), into the six output rows
/// [Sx, ∂Sx/∂u, ∂Sx/∂v, Sy, ∂Sy/∂u, ∂Sy/∂v].
#[inline(always)]
pub(super) fn u_pass(
    o: [&mut [f64]; 6],
    vrow: &[[f64; 4]],
    cols: &[(usize, [f64; 4], [f64; 4])],
    mask: [&[f64]; 2],
    inv_h: f64,
) {
    let [o0, o1, o2, o3, o4, o5] = o;
    for (cc, &(off, w, d)) in cols.iter().enumerate() {
        let t: &[[f64; 4]; 4] = vrow[off..off + 4].try_into().expect("4 taps");
        let mut a = [0.0f64; 4];
        let mut g = [0.0f64; 4];
        for b in 0..4 {
            for l in 0..4 {
                a[l] += w[b] * t[b][l];
                g[l] += d[b] * t[b][l];
            }
        }
        let (k0, k1) = (mask[0][cc], mask[1][cc]);
        o0[cc] = a[0] * k0;
        o1[cc] = g[0] * inv_h * k0;
        o2[cc] = a[2] * inv_h * k0;
        o3[cc] = a[1] * k1;
        o4[cc] = g[1] * inv_h * k1;
        o5[cc] = a[3] * inv_h * k1;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
pub(super) unsafe fn v_pass_avx2(
    vrow: &mut [[f64; 4]],
    taps: [&[[f64; 2]]; 4],
    w: &[f64; 4],
    d: &[f64; 4],
) {
    use std::arch::x86_64::*;
    let n = vrow.len();
    assert!(taps.iter().all(|t| t.len() == n));
    let wd = [0, 1, 2, 3].map(|b| _mm256_setr_pd(w[b], w[b], d[b], d[b]));
    for k in 0..n {
        let mut a = _mm256_setzero_pd();
        for b in 0..4 {
            // SAFETY: k < n = taps[b].len(); a node is two f64 (16 bytes).
            let t = _mm256_broadcast_pd(&*(taps[b].as_ptr().add(k) as *const __m128d));
            a = _mm256_add_pd(a, _mm256_mul_pd(wd[b], t));
        }
        // SAFETY: k < n = vrow.len(); a row element is four f64 (32 bytes).
        _mm256_storeu_pd(vrow.as_mut_ptr().add(k) as *mut f64, a);
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
pub(super) unsafe fn u_pass_avx2(
    o: [&mut [f64]; 6],
    vrow: &[[f64; 4]],
    cols: &[(usize, [f64; 4], [f64; 4])],
    mask: [&[f64]; 2],
    inv_h: f64,
) {
    use std::arch::x86_64::*;
    let n = cols.len();
    assert!(o.iter().all(|r| r.len() == n) && mask.iter().all(|m| m.len() == n));
    assert!(cols.iter().all(|c| c.0 + 4 <= vrow.len()));
    let [o0, o1, o2, o3, o4, o5] = o;
    let sa = _mm256_setr_pd(1.0, 1.0, inv_h, inv_h);
    let sg = _mm256_set1_pd(inv_h);
    for (cc, &(off, w, d)) in cols.iter().enumerate() {
        let mut a = _mm256_setzero_pd();
        let mut g = _mm256_setzero_pd();
        for b in 0..4 {
            // SAFETY: off + 4 ≤ vrow.len() (asserted above).
            let t = _mm256_loadu_pd(vrow.as_ptr().add(off + b) as *const f64);
            a = _mm256_add_pd(a, _mm256_mul_pd(_mm256_set1_pd(w[b]), t));
            g = _mm256_add_pd(g, _mm256_mul_pd(_mm256_set1_pd(d[b]), t));
        }
        let (k0, k1) = (mask[0][cc], mask[1][cc]);
        let k = _mm256_setr_pd(k0, k1, k0, k1);
        let a = _mm256_mul_pd(_mm256_mul_pd(a, sa), k);
        let g = _mm256_mul_pd(_mm256_mul_pd(g, sg), k);
        let mut av = [0.0f64; 4];
        let mut gv = [0.0f64; 4];
        _mm256_storeu_pd(av.as_mut_ptr(), a);
        _mm256_storeu_pd(gv.as_mut_ptr(), g);
        o0[cc] = av[0];
        o1[cc] = gv[0];
        o2[cc] = av[2];
        o3[cc] = av[1];
        o4[cc] = gv[1];
        o5[cc] = av[3];
    }
}

/// The AVX2 + FMA entry points of the sampler and the window sums: the same code as the
/// portable path (`*_impl`), compiled for AVX2 + FMA and chosen at run time by the dispatchers
/// in `normal.rs`.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::super::problem::FitData;
    use super::super::window::{Window, WindowAt};

    impl FitData<'_> {
        /// [`FitData::sample_window`] compiled for AVX2 + FMA.
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2,fma")]
        pub(in crate::analysis::fit) fn sample_window_avx2(
            &self,
            at: WindowAt,
            mask: Option<&[Vec<f64>; 2]>,
            out: &mut [f64],
        ) {
            self.sample_window_impl::<true>(at, mask, out)
        }
    }

    impl Window<'_> {
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2,fma")]
        pub(in crate::analysis::fit) fn own_sums_avx2(
            &self,
            res: &[Vec<f64>; 2],
            chans: &[usize],
            nx: usize,
        ) -> super::super::window::Sums {
            self.own_sums_impl(res, chans, nx)
        }

        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2,fma")]
        pub(in crate::analysis::fit) fn pair_sums_avx2(
            a: &Self,
            b: &Self,
            chans: &[usize],
        ) -> [[f64; 3]; 3] {
            Self::pair_sums_impl(a, b, chans)
        }
    }
}
