//! Covariance ↔ scale + rotation (symmetric eigendecomposition, Jacobi, f64).

/// Eigen-decompose a (nominally symmetric PSD) covariance: scales = sqrt(eigenvalues) (clamped ≥ 1e-6 so
/// degenerate or slightly non-PSD input still exports), rotation right-handed, quaternion (w, x, y, z).
pub fn covariance_to_scale_rotation(c: [[f64; 3]; 3]) -> ([f32; 3], [f32; 4]) {
    let finite = c.iter().flatten().all(|v| v.is_finite());
    if !finite {
        return ([1e-6; 3], [1.0, 0.0, 0.0, 0.0]);
    }
    let mut a = [[0f64; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            a[i][j] = 0.5 * (c[i][j] + c[j][i]);
        }
    }
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0f64]];
    for _sweep in 0..50 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        let scale = a[0][0].abs() + a[1][1].abs() + a[2][2].abs();
        if off <= 1e-15 * scale.max(1e-300) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q].abs() < 1e-300 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let cs = 1.0 / (t * t + 1.0).sqrt();
            let sn = t * cs;
            // A ← Jᵀ A J, V ← V J
            for k in 0..3 {
                let akp = a[k][p];
                let akq = a[k][q];
                a[k][p] = cs * akp - sn * akq;
                a[k][q] = sn * akp + cs * akq;
            }
            for k in 0..3 {
                let apk = a[p][k];
                let aqk = a[q][k];
                a[p][k] = cs * apk - sn * aqk;
                a[q][k] = sn * apk + cs * aqk;
            }
            for row in v.iter_mut() {
                let vp = row[p];
                let vq = row[q];
                row[p] = cs * vp - sn * vq;
                row[q] = sn * vp + cs * vq;
            }
        }
    }
    let det = v[0][0] * (v[1][1] * v[2][2] - v[1][2] * v[2][1]) - v[0][1] * (v[1][0] * v[2][2] - v[1][2] * v[2][0])
        + v[0][2] * (v[1][0] * v[2][1] - v[1][1] * v[2][0]);
    if det < 0.0 {
        for row in v.iter_mut() {
            row[2] = -row[2];
        }
    }
    let s = [0, 1, 2].map(|i| a[i][i].max(1e-12).sqrt().max(1e-6) as f32);
    (s, rot_to_quat(v))
}

/// Rotation matrix (columns = local axes) → unit quaternion (w, x, y, z), w ≥ 0.
fn rot_to_quat(r: [[f64; 3]; 3]) -> [f32; 4] {
    let tr = r[0][0] + r[1][1] + r[2][2];
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [0.25 * s, (r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s]
    } else if r[0][0] > r[1][1] && r[0][0] > r[2][2] {
        let s = (1.0 + r[0][0] - r[1][1] - r[2][2]).sqrt() * 2.0;
        [(r[2][1] - r[1][2]) / s, 0.25 * s, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s]
    } else if r[1][1] > r[2][2] {
        let s = (1.0 + r[1][1] - r[0][0] - r[2][2]).sqrt() * 2.0;
        [(r[0][2] - r[2][0]) / s, (r[0][1] + r[1][0]) / s, 0.25 * s, (r[1][2] + r[2][1]) / s]
    } else {
        let s = (1.0 + r[2][2] - r[0][0] - r[1][1]).sqrt() * 2.0;
        [(r[1][0] - r[0][1]) / s, (r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, 0.25 * s]
    };
    let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    let sgn = if q[0] < 0.0 { -1.0 } else { 1.0 };
    q.map(|x| (sgn * x / n) as f32)
}

/// R diag(s²) Rᵀ in f64 from a (normalised here) quaternion (w, x, y, z).
pub fn scale_rotation_to_covariance(s: [f32; 3], q: [f32; 4]) -> [[f64; 3]; 3] {
    let n = q.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
    let [w, x, y, z] = if n > 0.0 { q.map(|v| v as f64 / n) } else { [1.0, 0.0, 0.0, 0.0] };
    let r = [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ];
    let mut c = [[0f64; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = (0..3).map(|k| r[i][k] * r[j][k] * (s[k] as f64).powi(2)).sum();
        }
    }
    c
}
