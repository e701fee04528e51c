//! View selection over camera centres: farthest-point sampling for context views and nearest-k local groups.

use crate::Camera;

/// Where farthest-point sampling starts; every caller names its rule, so a scene's context views depend on the
/// rule and not on which command picked them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FpsStart {
    /// The first view (pytorch3d's `sample_farthest_points` without a random start): `render --num-context`.
    First,
    /// The point farthest from the centroid (the official `farthest_point_sample`): the evaluation index and the
    /// training sampler.
    FarthestFromCentroid,
}

/// Farthest-point sampling of `n` of `points` (at most all of them): the start of `start`, then repeatedly the
/// point whose squared distance to the chosen set is largest; ties go to the lowest index (`torch.max`).
/// Returns indices in selection order.
pub fn farthest_points(points: &[[f64; 3]], n: usize, start: FpsStart) -> Vec<usize> {
    let n = n.min(points.len());
    if n == 0 {
        return vec![];
    }
    let d2 = |a: &[f64; 3], b: &[f64; 3]| (0..3).map(|k| (a[k] - b[k]) * (a[k] - b[k])).sum::<f64>();
    let argmax = |v: &[f64]| (1..v.len()).fold(0, |best, i| if v[i] > v[best] { i } else { best });
    let first = match start {
        FpsStart::First => 0,
        FpsStart::FarthestFromCentroid => {
            let mut c = [0.0; 3];
            for p in points {
                for k in 0..3 {
                    c[k] += p[k];
                }
            }
            let c = c.map(|x| x / points.len() as f64);
            argmax(&points.iter().map(|p| d2(p, &c)).collect::<Vec<_>>())
        }
    };
    let mut chosen = vec![first];
    let mut dist: Vec<f64> = points.iter().map(|p| d2(p, &points[first])).collect();
    while chosen.len() < n {
        let best = argmax(&dist);
        chosen.push(best);
        for (d, p) in dist.iter_mut().zip(points) {
            *d = d.min(d2(p, &points[best]));
        }
    }
    chosen
}

/// [`farthest_points`] over camera centres.
pub fn farthest_views(cameras: &[Camera], n: usize, start: FpsStart) -> Vec<usize> {
    let centres: Vec<[f64; 3]> = cameras.iter().map(|c| c.center()).map(|p| [p.x, p.y, p.z]).collect();
    farthest_points(&centres, n, start)
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
            let sel = farthest_views(&cams, 8, FpsStart::First);
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
        assert_eq!(farthest_views(&cams, 3, FpsStart::First), vec![0, 4, 2]);
        assert_eq!(farthest_views(&cams, 10, FpsStart::First).len(), 5);
        assert!(farthest_views(&[], 3, FpsStart::First).is_empty());
        // From the centroid (x = 2): the ends are equally far, the lowest index wins, then the other end.
        assert_eq!(farthest_views(&cams, 3, FpsStart::FarthestFromCentroid), vec![0, 4, 2]);
        let shifted: Vec<_> = [0.0, 1.0, 2.0, 10.0].iter().map(|&x| cam_at(x, 0.0, 0.0)).collect();
        assert_eq!(farthest_views(&shifted, 2, FpsStart::FarthestFromCentroid), vec![3, 0]);
    }

    #[test]
    fn nearest_k_closed_form() {
        let cams: Vec<_> = [0.0, 1.0, 3.0, 7.0].iter().map(|&x| cam_at(x, 0.0, 0.0)).collect();
        let nk = nearest_k(&cams, 2);
        assert_eq!(nk, vec![vec![0, 1, 2], vec![1, 0, 2], vec![2, 1, 0], vec![3, 2, 1]]);
        assert_eq!(baseline_stats(&cams), (1.0, 7.0));
    }
}
