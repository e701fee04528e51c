//! The training view sampler, after the official `boundedv2_360`: a frame window of `gap` frames (uniform in
//! [min, max], no warm-up), context views by farthest-point sampling inside it, targets drawn without
//! replacement from the whole window (they may coincide with context views), both sorted, and a random
//! horizontal flip applied to images and cameras together.
//!
//! DL3DV videos hold a few hundred frames and the official window is 80–120 of them. The scenes made here are
//! closed loops of 32 views around the scene, so with `gap` omitted the window is the whole loop: the context
//! then spreads around the scene as at evaluation (5 views on a 32-view loop, the other 27 as targets).

use mvsplat360_camera::select::{farthest_views, FpsStart};
use mvsplat360_camera::Camera;
use rand::seq::SliceRandom;
use rand::Rng;

/// Which views one training example uses.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ViewSample {
    pub context: Vec<usize>,
    pub target: Vec<usize>,
    pub flip: bool,
}

#[derive(Debug, Clone, Copy)]
pub struct SamplerSettings {
    pub num_context: usize,
    pub num_target: usize,
    pub gap: Option<[usize; 2]>,
    /// Curriculum (the official sampler's `initial_*_distance_between_context_views`): the window starts at this
    /// gap and widens linearly to `gap` (the whole sequence when `gap` is None) as `warm_up` goes 0 → 1.
    pub gap_initial: Option<[usize; 2]>,
    /// Fraction of the curriculum's warm-up done, in [0, 1].
    pub warm_up: f64,
    pub closed_loop: bool,
    pub flip: bool,
}

impl SamplerSettings {
    /// The window's [min, max] gap for a sequence of `n` views at the current warm-up; None = the whole sequence.
    pub fn gap_now(&self, n: usize) -> Option<[usize; 2]> {
        let Some(init) = self.gap_initial else { return self.gap };
        let fin = self.gap.unwrap_or([n, n]);
        let t = self.warm_up.clamp(0.0, 1.0);
        let lerp = |a: usize, b: usize| (a as f64 + (b as f64 - a as f64) * t).round() as usize;
        Some([lerp(init[0], fin[0]), lerp(init[1], fin[1])])
    }
}

/// Draw one sample; `None` when the sequence is too short for the settings.
pub fn sample(cameras: &[Camera], s: &SamplerSettings, rng: &mut impl Rng) -> Option<ViewSample> {
    let n = cameras.len();
    if n < s.num_context.max(2) {
        return None;
    }
    let window: Vec<usize> = match s.gap_now(n) {
        None => (0..n).collect(),
        Some([lo, hi]) => {
            let hi = hi.min(if s.closed_loop { n } else { n - 1 });
            if hi < s.num_context || lo > hi {
                return None;
            }
            let g = rng.gen_range(lo.max(s.num_context)..=hi);
            if s.closed_loop {
                let start = rng.gen_range(0..n);
                (0..g.min(n)).map(|k| (start + k) % n).collect()
            } else {
                let start = rng.gen_range(0..=(n - 1 - g));
                (start..=start + g).collect()
            }
        }
    };
    let cams: Vec<Camera> = window.iter().map(|&i| cameras[i].clone()).collect();
    let mut context: Vec<usize> = farthest_views(&cams, s.num_context, FpsStart::FarthestFromCentroid).into_iter().map(|k| window[k]).collect();
    // Targets: without replacement from the whole window (they may coincide with context views, as official).
    let mut target = window.clone();
    target.shuffle(rng);
    target.truncate(s.num_target);
    context.sort_unstable();
    target.sort_unstable();
    let flip = s.flip && rng.gen_bool(0.5);
    Some(ViewSample { context, target, flip })
}

/// The camera of a horizontally flipped image: mirror the world by x → −x (conjugating c2w with
/// diag(−1, 1, 1), as the official `reflect_extrinsics`) and mirror the principal point.
pub fn flip_camera(c: &Camera) -> Camera {
    let mut m = c.c2w;
    for (r, row) in m.iter_mut().enumerate().take(3) {
        for (k, x) in row.iter_mut().enumerate() {
            if (r == 0) != (k == 0) {
                *x = -*x;
            }
        }
    }
    Camera { cx: c.width as f64 - c.cx, c2w: m, ..c.clone() }
}

/// Flip a (3,H,W) image left-right in place.
pub fn flip_image(data: &mut [f32], width: usize) {
    for row in data.chunks_exact_mut(width) {
        row.reverse();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;
    use rand::SeedableRng;

    fn ring(n: usize) -> Vec<Camera> {
        let t = Camera {
            fx: 60.0,
            fy: 60.0,
            cx: 40.0,
            cy: 20.0,
            width: 128,
            height: 64,
            c2w: [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
        };
        (0..n)
            .map(|i| {
                let a = std::f64::consts::TAU * i as f64 / n as f64;
                let eye = Vector3::new(10.0 * a.cos(), -3.0, 10.0 * a.sin());
                mvsplat360_camera::trajectory::look_at(&t, &eye, &Vector3::zeros(), &Vector3::new(0.0, -1.0, 0.0))
            })
            .collect()
    }

    #[test]
    fn whole_loop_context_is_spread_and_targets_disjoint() {
        let cams = ring(32);
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let s = SamplerSettings { num_context: 5, num_target: 27, gap: None, gap_initial: None, warm_up: 0.0, closed_loop: true, flip: false };
        let v = sample(&cams, &s, &mut rng).unwrap();
        assert_eq!(v.context.len(), 5);
        assert_eq!(v.target.len(), 27);
        let mut t = v.target.clone();
        t.dedup();
        assert_eq!(t.len(), 27, "targets are drawn without replacement");
        // FPS on a circle: opposite views, then the quarter points, then one eighth point → gaps of 4 or 8.
        let mut c = v.context.clone();
        c.sort();
        let gaps: Vec<usize> = (0..5).map(|k| (c[(k + 1) % 5] + 32 - c[k]) % 32).collect();
        assert!(gaps.iter().all(|&g| g == 4 || g == 8), "{c:?} {gaps:?}");
    }

    #[test]
    fn gap_window_bounds_every_view() {
        let cams = ring(200);
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let s = SamplerSettings { num_context: 2, num_target: 4, gap: Some([45, 60]), gap_initial: None, warm_up: 0.0, closed_loop: false, flip: true };
        for _ in 0..50 {
            let v = sample(&cams, &s, &mut rng).unwrap();
            let all: Vec<usize> = v.context.iter().chain(&v.target).copied().collect();
            let span = all.iter().max().unwrap() - all.iter().min().unwrap();
            assert!(span <= 60, "{all:?}");
            // Two context views by FPS from the view farthest from the centroid: the window's two ends.
            assert!(v.context[1] - v.context[0] >= 45, "{:?}", v.context);
        }
    }

    /// A point seen by a camera projects to the mirrored pixel in the flipped camera, with the mirrored world.
    #[test]
    fn flipped_camera_sees_the_mirrored_pixel() {
        let c = ring(8)[3].clone();
        let p = Vector3::new(1.0, -0.5, 2.0);
        let (u, v, z) = c.project(&p);
        let f = flip_camera(&c);
        let (u2, v2, z2) = f.project(&Vector3::new(-p.x, p.y, p.z));
        assert!((u2 - (c.width as f64 - u)).abs() < 1e-9 && (v2 - v).abs() < 1e-9 && (z2 - z).abs() < 1e-9, "{u},{v} → {u2},{v2}");
    }

    #[test]
    fn curriculum_widens_the_window_linearly_to_the_whole_loop() {
        let mut s = SamplerSettings { num_context: 5, num_target: 4, gap: None, gap_initial: Some([6, 10]), warm_up: 0.0, closed_loop: true, flip: false };
        assert_eq!(s.gap_now(32), Some([6, 10]));
        s.warm_up = 0.5;
        assert_eq!(s.gap_now(32), Some([19, 21]));
        s.warm_up = 2.0;
        assert_eq!(s.gap_now(32), Some([32, 32]));
        s.gap = Some([20, 24]);
        s.warm_up = 0.25;
        // 6 + 14/4 = 9.5 and 10 + 14/4 = 13.5, rounded half away from zero.
        assert_eq!(s.gap_now(32), Some([10, 14]));
        // Early in the curriculum every view of a sample lies in a window of at most 10 consecutive views.
        s.gap = None;
        s.warm_up = 0.0;
        let cams = ring(32);
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        for _ in 0..50 {
            let v = sample(&cams, &s, &mut rng).unwrap();
            let all: Vec<usize> = v.context.iter().chain(&v.target).copied().collect();
            // Circular span: the largest gap between sorted indices leaves the rest inside one window.
            let mut idx = all.clone();
            idx.sort_unstable();
            idx.dedup();
            let largest = (0..idx.len()).map(|k| (idx[(k + 1) % idx.len()] + 32 - idx[k]) % 32).max().unwrap();
            assert!(32 - largest < 10, "views {idx:?} span more than 10");
        }
    }
}
