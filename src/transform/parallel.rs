//! The forward FFT of a long real record on every core. realfft's plans are serial: a
//! 2^20-sample record's band (an FFT of 2^20 points, its smoothing and noise median) and
//! its padded spectrum (an FFT of 1.6 M points) took 15 and 16 of its preparation's 37 ms
//! on this project's 2-core machine, while the GPU backend waited for them. Here the complex FFT of length M = L/2 that a
//! real FFT of length L reduces to is cut by the four-step (Bailey) algorithm into a
//! matrix of a few rows (16 to 64) of M/rows columns: each column's short FFT, the
//! twiddles, then each row's long FFT (rustfft's plans), and the real record's bins from
//! the rows. Every pass is split among rayon's threads in tasks fixed by the length alone,
//! so the spectrum is the same to the last bit on any number of threads; it differs from
//! realfft's by rounding (measured within 2.7e-16 of the largest bin; the tests ask 2e-15).

use std::mem::MaybeUninit;

use num_complex::Complex64;
use rayon::prelude::*;

use super::complex_plan;

/// Real lengths from which a [`Spectrum`](super::Spectrum) is taken by [`real_spectrum`]
/// rather than by realfft: below, a record is one of many tracked side by side (a campaign
/// run's 46 080 points take 0.4 ms), and its spectrum stays realfft's to the bit.
pub const PARALLEL_MIN: usize = 1 << 18;

/// The environment variable that, set to `realfft`, takes every spectrum by realfft's serial
/// plan whatever its length: a measurement hook, to time both side by side on one machine.
pub const SERIAL_ENV: &str = "SKELID_SPECTRUM_FFT";

/// Whether a spectrum of `len` real points is taken by [`real_spectrum`]: from
/// [`PARALLEL_MIN`] points on, unless [`SERIAL_ENV`] asks for realfft's.
pub fn takes(len: usize) -> bool {
    static SERIAL: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    len >= PARALLEL_MIN
        && !*SERIAL.get_or_init(|| serial_asked(std::env::var(SERIAL_ENV).ok().as_deref()).0)
}

/// What the user should know of [`SERIAL_ENV`] as set (a value it does not understand,
/// which leaves the default), for the command line to print at start-up.
pub fn hook_note() -> Option<String> {
    serial_asked(std::env::var(SERIAL_ENV).ok().as_deref()).1
}

/// Whether [`SERIAL_ENV`]'s `value` asks for realfft's serial plan, and the note a value it
/// does not understand is answered with.
fn serial_asked(value: Option<&str>) -> (bool, Option<String>) {
    match value {
        None => (false, None),
        Some("realfft") => (true, None),
        Some(v) => (
            false,
            Some(format!(
                "{SERIAL_ENV}={v:?} is not understood: `realfft` takes every spectrum by \
                 realfft's serial plan; unset, spectra of {PARALLEL_MIN} points or more are \
                 taken on every core, as now"
            )),
        ),
    }
}

/// Columns of the matrix that one task of the first and last passes takes.
const COLUMNS_PER_TASK: usize = 512;

/// The one-sided spectrum, bins 0..=len/2 (unnormalised, e^{−2πi nk/len}), of `x` with
/// `mean` taken off every sample and zero-padded to `len` samples (even, at least
/// `x.len()`): realfft's definition, computed on every core.
pub fn real_spectrum(x: &[f64], mean: f64, len: usize) -> Vec<Complex64> {
    assert!(
        len >= 2 && len.is_multiple_of(2) && len >= x.len(),
        "a real FFT of {len} points for {} samples",
        x.len()
    );
    let m = len / 2;
    let (rows, cols) = split(m);
    let zero = Complex64::new(0.0, 0.0);
    // z[j] = x[2j] + i x[2j+1] of the padded record, its mean removed, as `rows` rows of
    // `cols`: z[cols r + c]. Three passes over memory, each reading and writing its rows in
    // order (a four-step of rows near √M, whose passes crossed the matrix a column at a
    // time, took twice realfft's time on one core):
    //
    // 1. For each block of columns c: the column's FFT over r (a short one), times the
    //    twiddle e^{−2πi c k / M}: y[k][c].
    let short = complex_plan(rows, false);
    let twiddle = Twiddles::new(m);
    let whole = x.len() / 2;
    let mut y: Vec<Complex64> = Vec::with_capacity(m);
    let mut pieces: Vec<Vec<&mut [MaybeUninit<Complex64>]>> = Vec::new();
    for row in y.spare_capacity_mut()[..m].chunks_mut(cols) {
        for (t, piece) in row.chunks_mut(COLUMNS_PER_TASK).enumerate() {
            if pieces.len() <= t {
                pieces.push(Vec::with_capacity(rows));
            }
            pieces[t].push(piece);
        }
    }
    pieces.into_par_iter().enumerate().for_each_init(
        || (Vec::new(), vec![zero; short.get_inplace_scratch_len()]),
        |(columns, scratch), (t, mut out)| {
            let c0 = t * COLUMNS_PER_TASK;
            let count = out[0].len();
            columns.clear();
            columns.resize(count * rows, zero);
            for r in 0..rows {
                let j = cols * r + c0;
                if j + count <= whole {
                    let pairs = x[2 * j..2 * (j + count)].chunks_exact(2);
                    for (c, p) in pairs.enumerate() {
                        columns[c * rows + r] = Complex64::new(p[0] - mean, p[1] - mean);
                    }
                } else {
                    let at = |i: usize| if i < x.len() { x[i] - mean } else { 0.0 };
                    for c in 0..count {
                        let i = 2 * (j + c);
                        columns[c * rows + r] = Complex64::new(at(i), at(i + 1));
                    }
                }
            }
            short.process_with_scratch(columns, scratch);
            for (k, row) in out.iter_mut().enumerate() {
                let mut w = twiddle.walk(c0 * k, k);
                for (c, o) in row.iter_mut().enumerate() {
                    o.write(columns[c * rows + k] * w.next());
                }
            }
        },
    );
    // SAFETY: the pieces cover the m elements, each once (every row cut into the same
    // columns), and every element of every piece was written just above.
    unsafe { y.set_len(m) };
    // 2. Each row's long FFT over c, in place: y[k][c'] = Z[k + rows c'].
    let long = complex_plan(cols, false);
    y.par_chunks_mut(cols).for_each_init(
        || vec![zero; long.get_inplace_scratch_len()],
        |scratch, row| long.process_with_scratch(row, scratch),
    );
    // 3. The real record's bins, X[k] and X[M − k] together from Z[k] and Z[M − k]
    //    (k = r + rows c lies in y[r][c]): X[k] = E + W O, X[M − k] = conj(E − W O).
    let half = Twiddles::new(len);
    let z_at = |k: usize| y[(k % rows) * cols + k / rows];
    let mut bins: Vec<Complex64> = Vec::with_capacity(m + 1);
    let out = &mut bins.spare_capacity_mut()[..m + 1];
    let z0 = y[0];
    out[0].write(Complex64::new(z0.re + z0.im, 0.0));
    out[m].write(Complex64::new(z0.re - z0.im, 0.0));
    // Bins 1..=pairs pair with M − k; the bin at M/2 (M even) with itself.
    let pairs = m.saturating_sub(1) / 2;
    let (low, rest) = out[1..m].split_at_mut(pairs);
    let (middle, high) = rest.split_at_mut(rest.len() - pairs);
    if let Some(o) = middle.first_mut() {
        let (even, odd) = halves(z_at(m / 2), z_at(m / 2), half.walk(m / 2, 1).next());
        o.write(even + odd);
    }
    low.par_chunks_mut(PAIRS_PER_TASK)
        .zip(high.par_rchunks_mut(PAIRS_PER_TASK))
        .enumerate()
        .for_each_init(Vec::new, |near, (t, (lo, hi))| {
            let (k0, count) = (1 + t * PAIRS_PER_TASK, lo.len());
            // The columns the task's bins and their mirrors lie in, each row's stretch
            // copied in order (read a column at a time, the rows at once left the
            // prefetchers behind).
            let q0 = m - k0;
            let (first, width) = (k0 / rows, (k0 + count - 1) / rows - k0 / rows + 1);
            let (mirror_first, mirror_width) = (
                (q0 + 1 - count) / rows,
                q0 / rows - (q0 + 1 - count) / rows + 1,
            );
            near.clear();
            for r in 0..rows {
                near.extend_from_slice(&y[r * cols + first..r * cols + first + width]);
            }
            let base = near.len();
            for r in 0..rows {
                let row = r * cols + mirror_first;
                near.extend_from_slice(&y[row..row + mirror_width]);
            }
            // Bin k0 + i at (r, c) counted up; its mirror M − k0 − i at (qr, qc) counted down.
            let (mut r, mut c) = (k0 % rows, k0 / rows - first);
            let (mut qr, mut qc) = (q0 % rows, q0 / rows - mirror_first);
            let mut w = half.walk(k0, 1);
            for i in 0..count {
                let zk = near[r * width + c];
                let zr = near[base + qr * mirror_width + qc];
                let (even, odd) = halves(zk, zr, w.next());
                lo[i].write(even + odd);
                hi[count - 1 - i].write((even - odd).conj());
                r += 1;
                if r == rows {
                    r = 0;
                    c += 1;
                }
                if qr == 0 {
                    qr = rows - 1;
                    qc = qc.wrapping_sub(1);
                } else {
                    qr -= 1;
                }
            }
        });
    // SAFETY: bins 0 and M were written first, 1..M by the pairs and the middle: low and
    // high are zipped chunk for chunk (equal lengths, high's from its end), and every
    // element of both was written in the loop.
    unsafe { bins.set_len(m + 1) };
    bins
}

/// Pairs of bins (k, M − k) that one task of the last pass takes.
const PAIRS_PER_TASK: usize = 8192;

/// E[k] = (Z[k] + Z̄[M−k])/2 and W O[k], O[k] = (Z[k] − Z̄[M−k])/(2i), for W = e^{−2πi k/L}:
/// bin k of the real record is E + W O, bin M − k conj(E − W O).
#[inline]
fn halves(zk: Complex64, zr: Complex64, w: Complex64) -> (Complex64, Complex64) {
    let zr = zr.conj();
    let even = 0.5 * (zk + zr);
    let d = zk - zr;
    (even, w * Complex64::new(0.5 * d.im, -0.5 * d.re))
}

/// M = rows × cols with rows the smallest divisor of M from 16 on (at most 64 for the
/// lengths of 2, 3 and 5 that a spectrum takes; 1 where M has none, a prime): enough
/// long rows for 16 threads, each a length rustfft plans well.
fn split(m: usize) -> (usize, usize) {
    let rows = (16..=64.min(m)).find(|r| m.is_multiple_of(*r)).unwrap_or(1);
    (rows, m / rows)
}

/// e^{−2πi j / N} for 0 ≤ j ≤ N from two tables of about √N values each, e^{−2πi (uB + t)/N}
/// = hi[u] · lo[t]: each factor within an ulp or two, their product within a few, where a
/// table of all N would take a long record's spectrum's size again.
struct Twiddles {
    step: usize,
    lo: Vec<Complex64>,
    hi: Vec<Complex64>,
}

impl Twiddles {
    fn new(n: usize) -> Twiddles {
        let step = ((n as f64).sqrt().ceil() as usize).max(1);
        let at = |j: usize| {
            Complex64::from_polar(1.0, -2.0 * std::f64::consts::PI * (j as f64) / n as f64)
        };
        Twiddles {
            step,
            lo: (0..step).map(at).collect(),
            hi: (0..=n / step).map(|u| at(u * step)).collect(),
        }
    }

    /// e^{−2πi j / N} for j = first, first + by, first + 2 by, …
    fn walk(&self, first: usize, by: usize) -> Walk<'_> {
        Walk {
            t: self,
            u: first / self.step,
            l: first % self.step,
            du: by / self.step,
            dl: by % self.step,
        }
    }
}

/// Successive twiddles of a [`Twiddles`], their index moved by a constant without a
/// division a value.
struct Walk<'a> {
    t: &'a Twiddles,
    u: usize,
    l: usize,
    du: usize,
    dl: usize,
}

impl Walk<'_> {
    #[inline]
    fn next(&mut self) -> Complex64 {
        let w = self.t.hi[self.u] * self.t.lo[self.l];
        self.l += self.dl;
        self.u += self.du;
        if self.l >= self.t.step {
            self.l -= self.t.step;
            self.u += 1;
        }
        w
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transform::serial_spectrum as realfft_spectrum;

    /// A record with a tone, a ramp and a deterministic wiggle, so no bin is special.
    fn record(n: usize) -> Vec<f64> {
        (0..n)
            .map(|i| {
                let t = i as f64;
                (0.0137 * t).sin()
                    + 1e-4 * t
                    + 0.3 * (((i * 7919) % 1009) as f64 / 1009.0 - 0.5)
                    + 2.5
            })
            .collect()
    }

    /// The DFT summed term by term, each angle reduced exactly (n k mod L) before its
    /// sine and cosine: the reference both FFTs are held to.
    fn naive_spectrum(x: &[f64], mean: f64, len: usize) -> Vec<Complex64> {
        (0..=len / 2)
            .map(|k| {
                x.iter()
                    .enumerate()
                    .map(|(i, v)| {
                        let j = (i * k) % len;
                        (v - mean)
                            * Complex64::from_polar(
                                1.0,
                                -2.0 * std::f64::consts::PI * j as f64 / len as f64,
                            )
                    })
                    .sum()
            })
            .collect()
    }

    /// Largest difference over the largest bin.
    fn relative(a: &[Complex64], b: &[Complex64]) -> f64 {
        assert_eq!(a.len(), b.len());
        let peak = b.iter().map(|v| v.norm()).fold(0.0, f64::max);
        a.iter()
            .zip(b)
            .map(|(p, q)| (p - q).norm())
            .fold(0.0, f64::max)
            / peak
    }

    #[test]
    fn the_four_step_spectrum_is_the_dft_at_lengths_of_every_shape() {
        // Prime, square, uneven and single-row M; padded and not.
        let mut worst: f64 = 0.0;
        let mut worst_realfft: f64 = 0.0;
        for (len, n) in [
            (2, 2),
            (4, 3),
            (6, 6),
            (12, 7),
            (26, 26),
            (98, 60),
            (154, 154),
            (194, 150),
            (512, 500),
            (1000, 999),
            (1536, 1000),
            (2048, 2048),
        ] {
            let x = record(n);
            let mean = crate::transform::mean_of(&x);
            let naive = naive_spectrum(&x, mean, len);
            let e = relative(&real_spectrum(&x, mean, len), &naive);
            let er = relative(&realfft_spectrum(&x, mean, len), &naive);
            assert!(e < 1e-14, "length {len}: {e:e} off the DFT");
            worst = worst.max(e);
            worst_realfft = worst_realfft.max(er);
        }
        println!("four-step within {worst:.1e} of the DFT, realfft within {worst_realfft:.1e}");
    }

    #[test]
    fn the_four_step_spectrum_is_realffts_at_long_lengths() {
        // The lengths a long record's preparation takes (2^20 and 1.6 M) and others of
        // 2, 3 and 5, each against realfft on the same padded samples.
        for (len, n) in [
            (PARALLEL_MIN, PARALLEL_MIN - 1000),
            (3 * (1 << 17), 300_000),
            (1 << 20, 1 << 20),
            (1_600_000, 1 << 20),
        ] {
            let x = record(n);
            let mean = crate::transform::mean_of(&x);
            let e = relative(
                &real_spectrum(&x, mean, len),
                &realfft_spectrum(&x, mean, len),
            );
            println!("length {len}: within {e:.1e} of realfft");
            assert!(e < 2e-15, "length {len}: {e:e}");
        }
    }

    #[test]
    fn the_measurement_hook_takes_realfft_and_names_a_value_it_does_not_understand() {
        assert_eq!(serial_asked(None), (false, None));
        assert_eq!(serial_asked(Some("realfft")), (true, None));
        let (serial, note) = serial_asked(Some("serial"));
        assert!(!serial);
        let note = note.expect("a note for a value not understood");
        assert!(note.contains("SKELID_SPECTRUM_FFT=\"serial\"") && note.contains("`realfft`"));
    }

    #[test]
    fn the_four_step_spectrum_is_the_same_on_any_number_of_threads() {
        let x = record(400_000);
        let mean = crate::transform::mean_of(&x);
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| real_spectrum(&x, mean, 480_000))
        };
        let one = on(1);
        for threads in [2, 3, 8] {
            assert!(on(threads) == one, "{threads} threads");
        }
    }
}
