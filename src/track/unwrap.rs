//! The phase made continuous: at each point the branch closest to the advance the frequency
//! predicts. The rule is a chain (each point's branch depends on the one before, through a
//! division), which on a 2^20-sample record's 156 000 grid points was 2 ms that no other
//! core shared, and on a campaign record an eighth of its track's completion. Each point's
//! turns are counted against its wrapped predecessor instead, which no point waits for, long
//! phases in blocks on every core; the result is checked against the chain's own rule and
//! comes out the same to the last bit.

use std::f64::consts::PI;

use rayon::prelude::*;

use crate::transform::exact_floor;

/// Points one task of a long phase's unwrapping takes (a campaign record's few thousand grid
/// points are one task).
const BLOCK: usize = 16_384;

/// Makes a wrapped phase continuous, choosing at each step the branch closest to the
/// advance predicted by the frequency; `time(i)` is point i's time (s).
pub(super) fn unwrap_phase(phase: &mut [f64], freq: &[f64], time: impl Fn(usize) -> f64 + Sync) {
    unwrap_in_blocks(phase, freq, &time, BLOCK);
}

/// The number of 2π turns that the chain's rule takes off point `i`'s wrapped phase `raw`,
/// given point `i − 1`'s unwrapped phase `prev`: the one expression both the chain and the
/// blocks' check evaluate.
#[inline]
fn turns(raw: f64, prev: f64, freq: &[f64], time: &impl Fn(usize) -> f64, i: usize) -> f64 {
    let dt = time(i) - time(i - 1);
    let predicted = prev + PI * (freq[i - 1] + freq[i]) * dt;
    let d = raw - predicted;
    exact_floor((d + PI) / (2.0 * PI))
}

/// The chain itself, from point `from` (whose predecessor is already unwrapped) to the end.
fn unwrap_chain(phase: &mut [f64], freq: &[f64], time: &impl Fn(usize) -> f64, from: usize) {
    for i in from.max(1)..phase.len() {
        phase[i] -= 2.0 * PI * turns(phase[i], phase[i - 1], freq, time, i);
    }
}

/// [`unwrap_phase`] in blocks of `block` points. Each point's turns are first counted against
/// its wrapped predecessor, as if that one needed no turn (no point waits for another, as in
/// the chain, whose every step waits for the division before it), and added up, within each
/// block and then over the blocks in order, to every point's turns. Taking a multiple of 2π
/// off the predecessor can round the chain's comparison differently, so every point is then
/// checked against the chain's rule with its predecessor as unwrapped; from the first point
/// that fails (none, in practice) the chain itself takes over. Every point before it
/// satisfied the rule, so the result is the chain's, bit for bit. Returns that first point
/// (`phase.len()` if none).
fn unwrap_in_blocks(
    phase: &mut [f64],
    freq: &[f64],
    time: &(impl Fn(usize) -> f64 + Sync),
    block: usize,
) -> usize {
    debug_assert!(block > 0, "blocks of no points");
    let n = phase.len();
    // Each block's turns, counted from its own start (the sums of small integers: exact).
    let mut own = vec![0.0; n];
    own.par_chunks_mut(block)
        .enumerate()
        .for_each(|(j, counts)| {
            let first = j * block;
            let mut k = 0.0;
            for (c, i) in counts.iter_mut().zip(first..) {
                // The first point is left as it is, as the chain leaves it.
                if i > 0 {
                    k += turns(phase[i], phase[i - 1], freq, time, i);
                }
                *c = k;
            }
        });
    // Each block's offset: the turns of the point before its start.
    let offsets: Vec<f64> = std::iter::once(0.0)
        .chain(own.chunks(block).scan(0.0, |k, counts| {
            *k += counts[counts.len() - 1];
            Some(*k)
        }))
        .take(n.div_ceil(block))
        .collect();
    // Each block checked against the chain's rule, its points' unwrapped values written
    // over its counts as it goes (the wrapped phase stays whole for the chain below); the
    // point before block j has `offsets[j]` turns.
    let raw: &[f64] = phase;
    let first_failure = own
        .par_chunks_mut(block)
        .enumerate()
        .filter_map(|(j, out)| {
            // offsets[0] is 0, and x − 0 is x to the bit (−0 and NaN included).
            let first = j * block;
            let mut prev = raw[first.saturating_sub(1)] - 2.0 * PI * offsets[j];
            for (o, i) in out.iter_mut().zip(first..) {
                if i == 0 {
                    // The chain leaves the first point as it is.
                    *o = raw[0];
                    continue;
                }
                let k = offsets[j] + *o;
                // `!=` also fails a NaN, whose chain the chain itself then carries on. Equal
                // values are equal bits here: neither a count of turns nor `k` (sums from
                // +0) is ever −0.
                if turns(raw[i], prev, freq, time, i) != k {
                    return Some(i);
                }
                prev = raw[i] - 2.0 * PI * k;
                *o = prev;
            }
            None
        })
        .min()
        .unwrap_or(n);
    phase[..first_failure].copy_from_slice(&own[..first_failure]);
    unwrap_chain(phase, freq, time, first_failure);
    first_failure
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// A swept tone's wrapped phase on an uneven grid, with phase noise of `jitter` rad.
    fn wrapped(n: usize, jitter: f64, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let t: Vec<f64> = (0..n)
            .map(|i| 1e-3 * i as f64 + 2e-4 * (i % 3) as f64)
            .collect();
        let f: Vec<f64> = t.iter().map(|&t| 40.0 + 30.0 * t).collect();
        let phase = t
            .iter()
            .map(|&t| {
                let p = 2.0 * PI * (40.0 * t + 15.0 * t * t) + rng.random_range(-jitter..=jitter);
                p - 2.0 * PI * (p / (2.0 * PI)).round()
            })
            .collect();
        (t, f, phase)
    }

    #[test]
    fn blocks_unwrap_to_the_chain_to_the_last_bit() {
        // Lengths around the blocks' edges; phase noise up to nearly ±π, where the branch
        // is a close call and a rounding could pick the other.
        for (n, jitter) in [
            (0, 0.1),
            (1, 0.1),
            (99, 0.1),
            (100, 3.0),
            (1000, 1.0),
            (1037, 3.1),
        ] {
            for block in [1, 7, 50, 64] {
                let (t, f, mut by_blocks) = wrapped(n, jitter, n as u64);
                let mut chain = by_blocks.clone();
                unwrap_chain(&mut chain, &f, &|i| t[i], 1);
                let failed = unwrap_in_blocks(&mut by_blocks, &f, &|i| t[i], block);
                assert_eq!(
                    bits(&by_blocks),
                    bits(&chain),
                    "{n} points, blocks of {block}"
                );
                // No close call in these phases: the blocks did the work, not the chain.
                assert_eq!(failed, n, "{n} points, blocks of {block}");
            }
        }
    }

    #[test]
    fn points_that_round_otherwise_than_the_chain_are_redone_by_it() {
        // A point whose advance lands on the branch's edge, nudged 1e-15 rad at a time:
        // counted against its wrapped predecessor (within ±π) and by the chain after the
        // earlier points' 90 turns (its predecessor near 565 rad, rounded 256 times more
        // coarsely) the comparison rounds one way for some nudges and the other way for
        // others, and the chain must take over there: at a block's first point, inside a
        // block, and in a phase that is one block.
        for (block, edge) in [(100, 300), (100, 250), (1000, 250)] {
            let n = 400;
            let time = |i: usize| 1e-3 * i as f64;
            let freq = vec![300.0; n];
            let (_, _, mut raw) = wrapped(n, 0.0, 5);
            for i in 1..n {
                let p = raw[i - 1] + 2.0 * PI * 300.0 * 1e-3 + 0.01 * (i % 7) as f64;
                raw[i] = p - 2.0 * PI * (p / (2.0 * PI)).round();
            }
            let mut unwrapped = raw.clone();
            unwrap_chain(&mut unwrapped, &freq, &time, 1);
            let prev = unwrapped[edge - 1];
            let at_edge =
                prev + PI * (freq[edge - 1] + freq[edge]) * (time(edge) - time(edge - 1)) - PI;
            let wrapped_edge = at_edge - 2.0 * PI * (at_edge / (2.0 * PI)).round();
            let mut redone = 0;
            for nudge in -300i64..=300 {
                let mut by_blocks = raw.clone();
                by_blocks[edge] = wrapped_edge + 1e-15 * nudge as f64;
                let mut chain = by_blocks.clone();
                unwrap_chain(&mut chain, &freq, &time, 1);
                let failed = unwrap_in_blocks(&mut by_blocks, &freq, &time, block);
                let case = format!("blocks of {block}, edge at {edge}, nudge {nudge}");
                assert_eq!(bits(&by_blocks), bits(&chain), "{case}");
                assert!(failed == n || failed == edge, "{case}: failed at {failed}");
                redone += usize::from(failed < n);
            }
            println!(
                "blocks of {block}, edge at {edge}: {redone} of 601 nudges redone by the chain"
            );
            assert!(
                redone > 0,
                "blocks of {block}, edge at {edge}: no nudge made the counts round otherwise \
                 than the chain"
            );
        }
    }

    #[test]
    fn a_nan_spoils_the_rest_of_the_phase_as_in_the_chain() {
        let (t, f, mut by_blocks) = wrapped(500, 0.5, 3);
        by_blocks[230] = f64::NAN;
        let mut chain = by_blocks.clone();
        unwrap_chain(&mut chain, &f, &|i| t[i], 1);
        let failed = unwrap_in_blocks(&mut by_blocks, &f, &|i| t[i], 64);
        assert_eq!(failed, 230, "the chain takes over at the NaN");
        assert_eq!(bits(&by_blocks), bits(&chain));
        assert!(by_blocks[229].is_finite() && by_blocks[499].is_nan());
    }
}
