//! The GPU backend against the CPU as reference, on whatever adapter wgpu finds: lavapipe
//! (Mesa's software Vulkan, installed by scripts/install-deps.sh) in CI, a real GPU where
//! there is one. No adapter is a failure here, not a skip: CI must test the GPU path.

use num_complex::{Complex32, Complex64};
use rand::{Rng, SeedableRng};
use skelid::gpu::fft::FftStage;
use skelid::gpu::Gpu;

fn gpu() -> Gpu {
    Gpu::new().unwrap_or_else(|e| panic!("{e}"))
}

/// Largest |GPU − rustfft (f64)| over the batch, relative to the largest |X|.
fn fft_error(gpu: &Gpu, stage: &FftStage, n: usize, batch: usize, inverse: bool, seed: u64) -> f64 {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let x: Vec<Complex64> = (0..n * batch)
        .map(|_| Complex64::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)))
        .collect();
    let mut ours: Vec<Complex32> = x
        .iter()
        .map(|c| Complex32::new(c.re as f32, c.im as f32))
        .collect();
    stage.transform(gpu, &mut ours, n, inverse).unwrap();
    let mut planner = rustfft::FftPlanner::<f64>::new();
    let plan = if inverse {
        planner.plan_fft_inverse(n)
    } else {
        planner.plan_fft_forward(n)
    };
    let mut truth = x.clone();
    plan.process(&mut truth);
    let scale = truth.iter().map(|c| c.norm()).fold(0.0, f64::max);
    truth
        .iter()
        .zip(&ours)
        .map(|(t, o)| (t - Complex64::new(f64::from(o.re), f64::from(o.im))).norm())
        .fold(0.0, f64::max)
        / scale
}

#[test]
fn gpu_fft_matches_rustfft_for_every_radix_length_and_batch() {
    let gpu = gpu();
    let stage = FftStage::new(&gpu);
    println!("adapter: {}", gpu.adapter_name());
    let mut worst: f64 = 0.0;
    // Single radices, their mixtures, the plan lengths of the transform (2^a·{9,10,12,15}),
    // and lengths far beyond one workgroup (multi-pass through global memory).
    let lengths = [
        2, 3, 4, 5, 8, 9, 15, 16, 25, 27, 30, 60, 64, 100, 243, 625, 1000, 1024, 1152, 2560, 3840,
        4096, 45_000, 65_536, 1_048_576,
    ];
    for (i, &n) in lengths.iter().enumerate() {
        for (batch, inverse) in [(1, false), (3, true), (7, false)] {
            if n * batch > 2_000_000 {
                continue;
            }
            let e = fft_error(&gpu, &stage, n, batch, inverse, i as u64);
            // f32 round-off grows like log n; 2e-6 per pass is generous for passes ≤ 20.
            let passes = skelid::gpu::fft::radices(n).unwrap().len().max(1) as f64;
            assert!(
                e < 2e-6 * passes,
                "n = {n}, batch {batch}, inverse {inverse}: error {e:.2e}"
            );
            worst = worst.max(e);
        }
    }
    println!("worst relative error over all lengths and batches: {worst:.2e}");
}

#[test]
fn gpu_fft_refuses_lengths_it_cannot_plan() {
    let gpu = gpu();
    let stage = FftStage::new(&gpu);
    let mut x = vec![Complex32::new(0.0, 0.0); 14];
    let e = stage.transform(&gpu, &mut x, 7, false).unwrap_err();
    assert!(e.to_string().contains("prime factor above 5"), "{e}");
}
