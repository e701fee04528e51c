//! Parity with the official rasterizer's golden fixtures (forward images, per-Gaussian buffers, gradients),
//! via both the cov3d and the scales+quats input paths. Forward tolerances from rasterizer/README.md; gradients
//! element-wise (see GRAD_ATOL / GRAD_RTOL).

use mvsplat360_splat::cpu::{self, CovInput, GradMode, PixelGrads};
use mvsplat360_testkit::get;

mod common;
use common::{check_abs, check_rel, clamped_jacobian, close_report, max_abs, to_planar, v32, vi, CovPath, Fixture};

/// Gradients, element-wise: |ours − fixture| ≤ GRAD_ATOL·max|fixture| + GRAD_RTOL·|fixture| (was max |Δ| ≤
/// 1e-4·max|fixture|). The absolute part stays proportional to the tensor's largest gradient because a small entry
/// is a sum of large per-pixel terms and carries their f32 noise: the smallest passing atol at GRAD_RTOL, measured
/// on `medium` (`small` needs less), is 6.4e-6 × max for means (README f32-vs-f64: 2.89e-3 of 453), 7.7e-6 for
/// means2d, 9.0e-6 for cov3d, 2.8e-6 for features, 1.6e-6 for SH, 9.5e-7 for opacities.
const GRAD_ATOL: f64 = 3e-5;
const GRAD_RTOL: f64 = 1e-4;

fn run(file: &str) {
    let fx = Fixture::load(file);
    let m = &fx.m;
    let cam = fx.settings.camera;
    let (h, w, nf) = (cam.height, cam.width, fx.nf);
    // Our projection matrices vs the fixture's.
    let fp: Vec<f32> = cam.full_proj().iter().flatten().copied().collect();
    check_abs("full_proj", &fp, &v32(get(m, "full_proj")), 1e-5);
    check_abs("campos", &cam.campos(), &v32(get(m, "campos")), 1e-5);
    let (settings, w1, w2) = (fx.settings, &fx.w1, &fx.w2);

    for path in [CovPath::Cov3d, CovPath::ScaleRot] {
        eprintln!("--- {file} via {path:?}");
        let inp = fx.inputs(path);
        let cov = inp.cov;
        let out = cpu::forward(&inp, &settings).unwrap();
        let radii: Vec<i64> = out.radii.iter().map(|&r| r as i64).collect();
        assert_eq!(radii, vi(get(m, "radii")), "radii differ");
        let tt: Vec<i64> = out.tiles_touched.iter().map(|&r| r as i64).collect();
        let tt_ref = vi(get(m, "tiles_touched"));
        let tt_bad = tt.iter().zip(&tt_ref).zip(&radii).filter(|((a, b), r)| **r > 0 && a != b).count();
        assert_eq!(tt_bad, 0, "tiles_touched differ for {tt_bad} visible Gaussians");
        let vis: Vec<bool> = radii.iter().map(|&r| r > 0).collect();
        let sel = |v: &[f32], c: usize| -> Vec<f32> { v.chunks(c).zip(&vis).filter(|(_, &ok)| ok).flat_map(|(x, _)| x.to_vec()).collect() };
        check_rel("means2d", &sel(&out.means2d, 2), &sel(&v32(get(m, "means2d")), 2), 1e-6);
        check_rel("depths", &sel(&out.depths, 1), &sel(&v32(get(m, "depths")), 1), 1e-6);
        check_rel("cov2d", &sel(&out.cov2d, 3), &sel(&v32(get(m, "cov2d")), 3), 1e-5);
        check_rel("conic", &sel(&out.conic, 3), &sel(&v32(get(m, "conic")), 3), 1e-5);
        check_abs("colors", &sel(&out.colors, 3), &sel(&v32(get(m, "colors")), 3), 1e-5);
        check_abs("rgb", &out.rgb, &to_planar(&v32(get(m, "rgb")), h, w, 3), 1e-4);
        check_abs("feat", &out.features, &to_planar(&v32(get(m, "feat")), h, w, nf), 1e-4);
        check_abs("alpha", &out.alpha, &v32(get(m, "alpha")), 1e-4);
        check_abs("depth", &out.depth, &v32(get(m, "depth")), 1e-4);
        check_abs("final_T", &out.final_t, &v32(get(m, "final_T")), 1e-4);
        let nc_ref = vi(get(m, "n_contrib"));
        let nc_bad = out.n_contrib.iter().zip(&nc_ref).filter(|(a, b)| **a as i64 != **b).count();
        eprintln!("n_contrib: {nc_bad} pixels differ");
        assert!(nc_bad <= 5, "n_contrib differs at {nc_bad} pixels");

        let pg = PixelGrads { rgb: w1, features: w2, alpha: None, depth: None };
        let g = cpu::backward(&inp, &settings, &out, &pg, GradMode::Official).unwrap();
        let mut grads: Vec<(&str, &[f32], usize)> = vec![
            ("grad_means", &g.means[..], 3),
            ("grad_opacities", &g.opacities[..], 1),
            ("grad_sh", &g.sh[..], 3 * fx.sh_coeffs),
            ("grad_features", &g.features[..], nf),
            ("grad_means2d_ndc", &g.means2d_ndc[..], 2),
        ];
        match cov {
            CovInput::Cov3d(_) => grads.push(("grad_cov3d", &g.cov3d[..], 6)),
            CovInput::ScaleRot { .. } => {
                grads.push(("grad_scales", g.scales.as_deref().unwrap(), 3));
                grads.push(("grad_quats", g.quats.as_deref().unwrap(), 4));
            }
        }
        let mut fails = Vec::new();
        for &(name, ours, _) in &grads {
            let want = v32(get(m, name));
            // Element-wise; atol is a fraction of the tensor's largest gradient (entries near zero only carry
            // the f32 noise of the large terms they sum).
            fails.extend(close_report(name, ours, &want, GRAD_ATOL * max_abs(&want), GRAD_RTOL));
        }
        // The fixtures do not test the official clamped-Jacobian gradient: `medium`'s only visible Gaussian outside
        // the 1.3·tan(fov) cone has all-zero gradients (it blends into no pixel), `small` has none, and the hidden
        // variant's six are not in this folder. tests/grad_check.rs checks that gradient against finite differences.
        let clamped = clamped_jacobian(&fx.means, &radii, &cam);
        let zero = clamped.iter().all(|&i| v32(get(m, "grad_means"))[3 * i..3 * i + 3].iter().all(|&x| x == 0.0));
        eprintln!("visible clamped-Jacobian Gaussians: {clamped:?} (fixture gradients all zero: {zero})");
        mvsplat360_testkit::assert_no_failures(&format!("{file} gradients via {path:?}"), &fails);
        // Determinism: a second backward gives bit-identical gradients.
        let g2 = cpu::backward(&inp, &settings, &out, &pg, GradMode::Official).unwrap();
        assert_eq!(g.means, g2.means);
        assert_eq!(g.cov3d, g2.cov3d);
    }
}

#[test]
fn parity_small() {
    run("small.safetensors");
}

#[test]
fn parity_medium() {
    run("medium.safetensors");
}
