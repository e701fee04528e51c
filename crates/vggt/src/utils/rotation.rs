//! Quaternions with the real part last (`xyzw`), as upstream's `rotation.py`.

/// `quat_to_mat`: any non-zero quaternion (it need not be unit: the `2/|q|²` factor normalises), row-major.
pub fn quat_to_mat(q: [f64; 4]) -> [[f64; 3]; 3] {
    let [i, j, k, r] = q;
    let two_s = 2.0 / (i * i + j * j + k * k + r * r);
    [
        [1.0 - two_s * (j * j + k * k), two_s * (i * j - k * r), two_s * (i * k + j * r)],
        [two_s * (i * j + k * r), 1.0 - two_s * (i * i + k * k), two_s * (j * k - i * r)],
        [two_s * (i * k - j * r), two_s * (j * k + i * r), 1.0 - two_s * (i * i + j * j)],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quaternion_closed_forms() {
        // 90° about z (xyzw = (0, 0, sin 45°, cos 45°)), scaled by 3: x → y.
        let s = std::f64::consts::FRAC_1_SQRT_2 * 3.0;
        let m = quat_to_mat([0.0, 0.0, s, s]);
        let want = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        for r in 0..3 {
            for c in 0..3 {
                assert!((m[r][c] - want[r][c]).abs() < 1e-12, "{m:?}");
            }
        }
    }
}
