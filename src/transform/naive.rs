//! The plain full-length wavelet transform: one inverse FFT of the padded length per scale,
//! every bin of the positive half kept. It is the reference the band-limited transform is
//! tested against, and the baseline of `skelid bench --transform`.

use num_complex::Complex64;

use super::{complex_plan, Morlet, Spectrum};

/// W(s, t) at every padded sample t = 0..L for one scale `s`.
pub fn scale(spec: &Spectrum, wavelet: &Morlet, s: f64, buf: &mut Vec<Complex64>) {
    let l = spec.padded_len;
    buf.clear();
    buf.resize(l, Complex64::new(0.0, 0.0));
    let norm = 2.0 / l as f64;
    for (m, b) in spec.all_bins().iter().enumerate().skip(1) {
        buf[m] = b * (norm * wavelet.spectrum(s, spec.bin_freq(m)));
    }
    complex_plan(l, true).process(buf);
}

/// Per-sample argmax ridge over the full scalogram: returns (index of the maximising
/// frequency, |W| there) per sample. The scales are shared among threads, each keeping only
/// its own O(N) maximum, merged at the end — the fair multi-core baseline for benchmarks.
pub fn argmax_ridge(spec: &Spectrum, wavelet: &Morlet, freqs: &[f64]) -> (Vec<usize>, Vec<f64>) {
    use rayon::prelude::*;
    let n = spec.samples;
    let empty = || (vec![0usize; n], vec![f64::NEG_INFINITY; n], Vec::new());
    let (best, peak, _) = freqs
        .par_iter()
        .enumerate()
        .fold(empty, |(mut best, mut peak, mut buf), (k, &f)| {
            scale(spec, wavelet, wavelet.scale_for(f), &mut buf);
            for t in 0..n {
                let a = buf[t].norm();
                if a > peak[t] {
                    peak[t] = a;
                    best[t] = k;
                }
            }
            (best, peak, buf)
        })
        .reduce(empty, |(mut b1, mut p1, _), (b2, p2, _)| {
            for t in 0..n {
                if p2[t] > p1[t] || (p2[t] == p1[t] && b2[t] < b1[t]) {
                    p1[t] = p2[t];
                    b1[t] = b2[t];
                }
            }
            (b1, p1, Vec::new())
        });
    (best, peak)
}
