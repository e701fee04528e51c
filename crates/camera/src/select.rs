//! View selection over camera centres: farthest-point sampling for context views and nearest-k local groups.

use crate::Camera;

/// Farthest-point sampling of `n` views over camera centres.
///
/// Start rule: index 0 (as pytorch3d's `sample_farthest_points` without random start), then repeatedly the view
/// whose distance to the chosen set is largest; ties go to the lowest index. Returns indices in selection order.
pub fn farthest_point_sampling(cameras: &[Camera], n: usize) -> Vec<usize> {
    let centres: Vec<_> = cameras.iter().map(|c| c.center()).collect();
    let n = n.min(centres.len());
    if n == 0 {
        return vec![];
    }
    let mut chosen = vec![0usize];
    let mut min_d: Vec<f64> = centres.iter().map(|p| (p - centres[0]).norm()).collect();
    while chosen.len() < n {
        let mut best = 0;
        for i in 1..centres.len() {
            if min_d[i] > min_d[best] {
                best = i;
            }
        }
        chosen.push(best);
        for (i, d) in min_d.iter_mut().enumerate() {
            *d = d.min((centres[i] - centres[best]).norm());
        }
    }
    chosen
}

/// For every view, itself followed by its `k` nearest other views by centre distance (stable on ties),
/// i.e. the first `k + 1` columns of the official `cameras_dist_index`.
pub fn nearest_k(cameras: &[Camera], k: usize) -> Vec<Vec<usize>> {
    let centres: Vec<_> = cameras.iter().map(|c| c.center()).collect();
    (0..centres.len())
        .map(|i| {
            let mut order: Vec<usize> = (0..centres.len()).collect();
            order.sort_by(|&a, &b| {
                let da = (centres[a] - centres[i]).norm();
                let db = (centres[b] - centres[i]).norm();
                // Self first even when another camera shares the centre.
                (a != i).cmp(&(b != i)).then(da.total_cmp(&db))
            });
            order.truncate(k + 1);
            order
        })
        .collect()
}

/// Mean distance between consecutive views of the FPS order: a rough baseline for summaries.
pub fn baseline_stats(cameras: &[Camera]) -> (f64, f64) {
    let mut min = f64::INFINITY;
    let mut max: f64 = 0.0;
    for (i, a) in cameras.iter().enumerate() {
        for b in cameras.iter().skip(i + 1) {
            let d = (a.center() - b.center()).norm();
            min = min.min(d);
            max = max.max(d);
        }
    }
    if cameras.len() < 2 {
        (0.0, 0.0)
    } else {
        (min, max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam_at(x: f64, y: f64, z: f64) -> Camera {
        let mut c = crate::camera::test_camera();
        c.c2w[0][3] = x;
        c.c2w[1][3] = y;
        c.c2w[2][3] = z;
        c
    }

    fn pseudo_random_cams(n: usize, seed: u64) -> Vec<Camera> {
        let mut s = seed;
        let mut next = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 11) as f64) / ((1u64 << 53) as f64) * 10.0 - 5.0
        };
        (0..n).map(|_| cam_at(next(), next(), next())).collect()
    }

    #[test]
    fn fps_matches_brute_force_greedy_rule() {
        for seed in 0..5 {
            let cams = pseudo_random_cams(30, seed);
            let sel = farthest_point_sampling(&cams, 8);
            assert_eq!(sel[0], 0);
            assert_eq!(sel.len(), 8);
            // Brute force: each pick maximises the min distance to all earlier picks over all views.
            for step in 1..sel.len() {
                let score = |i: usize| sel[..step].iter().map(|&j| (cams[i].center() - cams[j].center()).norm()).fold(f64::INFINITY, f64::min);
                let best = (0..cams.len()).map(score).fold(0.0, f64::max);
                assert!((score(sel[step]) - best).abs() < 1e-12, "seed {seed} step {step}");
            }
            let mut uniq = sel.clone();
            uniq.sort();
            uniq.dedup();
            assert_eq!(uniq.len(), sel.len());
        }
    }

    #[test]
    fn fps_on_a_line_picks_ends_then_middle() {
        let cams: Vec<_> = (0..5).map(|i| cam_at(i as f64, 0.0, 0.0)).collect();
        assert_eq!(farthest_point_sampling(&cams, 3), vec![0, 4, 2]);
        assert_eq!(farthest_point_sampling(&cams, 10).len(), 5);
        assert!(farthest_point_sampling(&[], 3).is_empty());
    }

    #[test]
    fn nearest_k_closed_form() {
        let cams: Vec<_> = [0.0, 1.0, 3.0, 7.0].iter().map(|&x| cam_at(x, 0.0, 0.0)).collect();
        let nk = nearest_k(&cams, 2);
        assert_eq!(nk, vec![vec![0, 1, 2], vec![1, 0, 2], vec![2, 1, 0], vec![3, 2, 1]]);
        assert_eq!(baseline_stats(&cams), (1.0, 7.0));
    }
}
