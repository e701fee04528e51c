//! Procedural training scenes: textured objects (spheres, rotated boxes, cylinders) on a textured ground,
//! sometimes inside walls, under a sky, ray cast with Lambert shading and hard shadows, seen from a closed
//! loop of cameras around the scene (a 360° capture). Deterministic for a seed, whatever the thread count.
//!
//! World axes: up is −y (as the pipeline's orbit helpers assume); the ground is the plane y = 0 and objects
//! stand on it (y ≤ 0). Cameras look at the scene centre from ≈ 10 units, the distance `render --scene-scale
//! auto` normalises user scenes to.

use mvsplat360_camera::{trajectory, Camera};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

type V3 = Vector3<f64>;

pub struct GenView {
    /// (3, H, W) channel-major, values in [0, 1].
    pub image: Vec<f32>,
    /// (H, W) distance from the camera centre along each pixel centre's ray (the encoder's depth
    /// convention); infinite where the ray sees the sky.
    pub depth: Vec<f32>,
    pub camera: Camera,
}

pub struct GenScene {
    pub name: String,
    pub views: Vec<GenView>,
    pub near: f32,
    pub far: f32,
}

#[derive(Debug, Clone, Copy)]
pub struct GenOptions {
    pub views: usize,
    pub width: u32,
    pub height: u32,
    /// Supersampling per axis.
    pub samples: u32,
}

impl Default for GenOptions {
    fn default() -> Self {
        Self { views: 32, width: 256, height: 128, samples: 2 }
    }
}

#[derive(Debug, Clone, Copy)]
enum Pattern {
    Checker(f64),
    Stripes(f64, usize),
    Noise(f64),
    Rings(f64),
}

#[derive(Debug, Clone, Copy)]
struct Material {
    a: V3,
    b: V3,
    pattern: Pattern,
    seed: u32,
}

#[derive(Debug, Clone, Copy)]
enum Shape {
    Sphere {
        c: V3,
        r: f64,
    },
    /// Box with half extents `h`, rotated by `angle` about the vertical axis.
    Cuboid {
        c: V3,
        h: V3,
        angle: f64,
    },
    /// Vertical cylinder standing on the ground.
    Cylinder {
        c: V3,
        r: f64,
        height: f64,
    },
    /// Wall: the plane n·p = d (n horizontal), visible from the side n points to.
    Wall {
        n: V3,
        d: f64,
    },
}

struct Object {
    shape: Shape,
    mat: Material,
}

struct World {
    objects: Vec<Object>,
    ground: Material,
    light: V3,
    sky_top: V3,
    sky_horizon: V3,
    ambient: f64,
}

fn hash(x: i64, y: i64, z: i64, s: u32) -> f64 {
    let mut h = (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (z as u64).wrapping_mul(0x1656_67B1_9E37_79F9)
        ^ (s as u64) << 7;
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 29;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Trilinear value noise in [0, 1].
fn value_noise(p: V3, s: u32) -> f64 {
    let f = p.map(|v| v.floor());
    let t = p - f;
    let sm = t.map(|v| v * v * (3.0 - 2.0 * v));
    let (x0, y0, z0) = (f.x as i64, f.y as i64, f.z as i64);
    let mut acc = 0.0;
    for dz in 0..2 {
        for dy in 0..2 {
            for dx in 0..2 {
                let w = (if dx == 1 { sm.x } else { 1.0 - sm.x }) * (if dy == 1 { sm.y } else { 1.0 - sm.y }) * (if dz == 1 { sm.z } else { 1.0 - sm.z });
                acc += w * hash(x0 + dx, y0 + dy, z0 + dz, s);
            }
        }
    }
    acc
}

fn fbm(p: V3, s: u32) -> f64 {
    (value_noise(p, s) * 0.55 + value_noise(p * 2.03, s + 1) * 0.3 + value_noise(p * 4.1, s + 2) * 0.15).clamp(0.0, 1.0)
}

impl Material {
    fn color(&self, p: V3) -> V3 {
        let t = match self.pattern {
            Pattern::Checker(sc) => {
                let q = p / sc;
                let k = q.x.floor() as i64 + q.y.floor() as i64 + q.z.floor() as i64;
                if k.rem_euclid(2) == 0 {
                    0.15
                } else {
                    0.85
                }
            }
            Pattern::Stripes(sc, axis) => 0.5 + 0.5 * (p[axis] / sc * std::f64::consts::TAU).sin(),
            Pattern::Noise(sc) => fbm(p / sc, self.seed),
            Pattern::Rings(sc) => 0.5 + 0.5 * ((p.x * p.x + p.z * p.z).sqrt() / sc * std::f64::consts::TAU).sin(),
        };
        // Fine grain so that flat areas still have texture to match.
        let grain = 0.85 + 0.3 * value_noise(p * 9.0, self.seed ^ 0x55);
        (self.a * (1.0 - t) + self.b * t) * grain
    }
}

struct Hit {
    t: f64,
    n: V3,
    /// Index into `objects`, or `usize::MAX` for the ground.
    id: usize,
}

fn rot_y(v: V3, a: f64) -> V3 {
    let (s, c) = a.sin_cos();
    V3::new(c * v.x + s * v.z, v.y, -s * v.x + c * v.z)
}

fn intersect(shape: &Shape, o: V3, d: V3) -> Option<(f64, V3)> {
    const EPS: f64 = 1e-6;
    match *shape {
        Shape::Sphere { c, r } => {
            let oc = o - c;
            let b = oc.dot(&d);
            let disc = b * b - (oc.dot(&oc) - r * r);
            if disc < 0.0 {
                return None;
            }
            let sq = disc.sqrt();
            let t = if -b - sq > EPS { -b - sq } else { -b + sq };
            (t > EPS).then(|| (t, (o + d * t - c) / r))
        }
        Shape::Cuboid { c, h, angle } => {
            let lo = rot_y(o - c, -angle);
            let ld = rot_y(d, -angle);
            let (mut tmin, mut tmax) = (f64::NEG_INFINITY, f64::INFINITY);
            let mut axis = 0;
            for k in 0..3 {
                if ld[k].abs() < 1e-12 {
                    if lo[k].abs() > h[k] {
                        return None;
                    }
                    continue;
                }
                let (mut t0, mut t1) = ((-h[k] - lo[k]) / ld[k], (h[k] - lo[k]) / ld[k]);
                if t0 > t1 {
                    std::mem::swap(&mut t0, &mut t1);
                }
                if t0 > tmin {
                    tmin = t0;
                    axis = k;
                }
                tmax = tmax.min(t1);
            }
            if tmin > tmax || tmin <= EPS {
                return None;
            }
            let mut n = V3::zeros();
            n[axis] = -ld[axis].signum();
            Some((tmin, rot_y(n, angle)))
        }
        Shape::Cylinder { c, r, height } => {
            // Side: (x − cx)² + (z − cz)² = r², −height ≤ y ≤ 0 (up is −y); top cap at y = −height.
            let mut best: Option<(f64, V3)> = None;
            let (ox, oz) = (o.x - c.x, o.z - c.z);
            let a = d.x * d.x + d.z * d.z;
            if a > 1e-12 {
                let b = ox * d.x + oz * d.z;
                let disc = b * b - a * (ox * ox + oz * oz - r * r);
                if disc >= 0.0 {
                    let t = (-b - disc.sqrt()) / a;
                    let y = o.y + d.y * t;
                    if t > EPS && y <= 0.0 && y >= -height {
                        let p = o + d * t;
                        best = Some((t, V3::new(p.x - c.x, 0.0, p.z - c.z) / r));
                    }
                }
            }
            if d.y.abs() > 1e-12 {
                let t = (-height - o.y) / d.y;
                let p = o + d * t;
                if t > EPS && (p.x - c.x).powi(2) + (p.z - c.z).powi(2) <= r * r && best.is_none_or(|(bt, _)| t < bt) {
                    best = Some((t, V3::new(0.0, -1.0, 0.0)));
                }
            }
            best
        }
        Shape::Wall { n, d: dd } => {
            let den = n.dot(&d);
            if den >= -1e-12 {
                return None;
            }
            let t = (dd - n.dot(&o)) / den;
            (t > EPS).then_some((t, n))
        }
    }
}

impl World {
    fn hit(&self, o: V3, d: V3) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        if d.y > 1e-12 {
            let t = -o.y / d.y;
            if t > 1e-6 {
                best = Some(Hit { t, n: V3::new(0.0, -1.0, 0.0), id: usize::MAX });
            }
        }
        for (i, ob) in self.objects.iter().enumerate() {
            if let Some((t, n)) = intersect(&ob.shape, o, d) {
                if best.as_ref().is_none_or(|b| t < b.t) {
                    best = Some(Hit { t, n, id: i });
                }
            }
        }
        best
    }

    fn shade(&self, o: V3, d: V3) -> V3 {
        let Some(h) = self.hit(o, d) else {
            let up = (-d.y).clamp(-1.0, 1.0) * 0.5 + 0.5;
            return self.sky_horizon * (1.0 - up) + self.sky_top * up;
        };
        let p = o + d * h.t;
        let mat = if h.id == usize::MAX { &self.ground } else { &self.objects[h.id].mat };
        let albedo = mat.color(p);
        let n = if h.n.dot(&d) > 0.0 { -h.n } else { h.n };
        let mut diffuse = n.dot(&self.light).max(0.0);
        if diffuse > 0.0 && self.hit(p + n * 1e-4, self.light).is_some() {
            diffuse = 0.0;
        }
        albedo * (self.ambient + (1.0 - self.ambient) * diffuse)
    }
}

fn rand_color(rng: &mut impl Rng) -> V3 {
    // Saturated or pastel at random, never black.
    let h = rng.gen_range(0.0..6.0);
    let s = rng.gen_range(0.2..0.9);
    let v = rng.gen_range(0.45..1.0);
    let c = v * s;
    let x = c * (1.0 - ((h % 2.0) - 1.0f64).abs());
    let (r, g, b) = match h as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    V3::new(r, g, b) + V3::repeat(v - c)
}

fn rand_material(rng: &mut impl Rng, scale: f64) -> Material {
    let pattern = match rng.gen_range(0..4) {
        0 => Pattern::Checker(scale * rng.gen_range(0.3..1.0)),
        1 => Pattern::Stripes(scale * rng.gen_range(0.3..1.2), rng.gen_range(0..3)),
        2 => Pattern::Noise(scale * rng.gen_range(0.2..0.8)),
        _ => Pattern::Rings(scale * rng.gen_range(0.3..1.0)),
    };
    Material { a: rand_color(rng), b: rand_color(rng), pattern, seed: rng.gen() }
}

fn build_world(rng: &mut impl Rng) -> World {
    let mut objects: Vec<Object> = Vec::new();
    let n = rng.gen_range(3..=8);
    let mut placed: Vec<(f64, f64, f64)> = Vec::new();
    for _ in 0..n * 4 {
        if objects.len() >= n {
            break;
        }
        let size = rng.gen_range(0.5..1.6);
        let (rad, ang) = (rng.gen_range(0.0..3.2), rng.gen_range(0.0..std::f64::consts::TAU));
        let (x, z) = (rad * ang.cos(), rad * ang.sin());
        if placed.iter().any(|&(px, pz, ps)| ((px - x).powi(2) + (pz - z).powi(2)).sqrt() < 0.8 * (ps + size)) {
            continue;
        }
        placed.push((x, z, size));
        let shape = match rng.gen_range(0..3) {
            0 => Shape::Sphere { c: V3::new(x, -size, z), r: size },
            1 => {
                let h = V3::new(size * rng.gen_range(0.5..1.0), size * rng.gen_range(0.4..1.3), size * rng.gen_range(0.5..1.0));
                Shape::Cuboid { c: V3::new(x, -h.y, z), h, angle: rng.gen_range(0.0..std::f64::consts::PI) }
            }
            _ => Shape::Cylinder { c: V3::new(x, 0.0, z), r: size * rng.gen_range(0.4..0.9), height: size * rng.gen_range(1.0..3.0) },
        };
        objects.push(Object { shape, mat: rand_material(rng, 1.0) });
    }
    // Sometimes a room: walls beyond the camera loop.
    if rng.gen_bool(0.5) {
        let d = rng.gen_range(14.0..20.0);
        let rot = rng.gen_range(0.0..std::f64::consts::FRAC_PI_2);
        for k in 0..4 {
            if rng.gen_bool(0.85) {
                let a = rot + k as f64 * std::f64::consts::FRAC_PI_2;
                // Inward normal; the wall is the plane n·p = −d.
                let n = V3::new(-a.cos(), 0.0, -a.sin());
                objects.push(Object { shape: Shape::Wall { n, d: -d }, mat: rand_material(rng, 3.0) });
            }
        }
    }
    let elev: f64 = rng.gen_range(0.5..1.2);
    let az = rng.gen_range(0.0..std::f64::consts::TAU);
    let light = V3::new(elev.cos() * az.cos(), -elev.sin(), elev.cos() * az.sin()).normalize();
    World {
        objects,
        ground: rand_material(rng, 2.0),
        light,
        sky_top: V3::new(rng.gen_range(0.3..0.6), rng.gen_range(0.5..0.75), rng.gen_range(0.8..1.0)),
        sky_horizon: V3::new(rng.gen_range(0.75..0.95), rng.gen_range(0.75..0.95), rng.gen_range(0.8..1.0)),
        ambient: rng.gen_range(0.25..0.45),
    }
}

fn render_view(world: &World, cam: &Camera, samples: u32) -> (Vec<f32>, Vec<f32>) {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let r = cam.rotation();
    let o = cam.center();
    let s = samples.max(1) as usize;
    let ray = |u: f64, v: f64| (r * V3::new((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0)).normalize();
    let rows: Vec<Vec<([f32; 3], f32)>> = (0..h)
        .into_par_iter()
        .map(|y| {
            (0..w)
                .map(|x| {
                    let mut acc = V3::zeros();
                    for sy in 0..s {
                        for sx in 0..s {
                            let u = x as f64 + (sx as f64 + 0.5) / s as f64;
                            let v = y as f64 + (sy as f64 + 0.5) / s as f64;
                            acc += world.shade(o, ray(u, v));
                        }
                    }
                    let c = acc / (s * s) as f64;
                    let depth = world.hit(o, ray(x as f64 + 0.5, y as f64 + 0.5)).map_or(f32::INFINITY, |hit| hit.t as f32);
                    ([c.x.clamp(0.0, 1.0) as f32, c.y.clamp(0.0, 1.0) as f32, c.z.clamp(0.0, 1.0) as f32], depth)
                })
                .collect()
        })
        .collect();
    let mut img = vec![0f32; 3 * w * h];
    let mut depth = vec![0f32; w * h];
    for (y, row) in rows.iter().enumerate() {
        for (x, (c, d)) in row.iter().enumerate() {
            for k in 0..3 {
                img[k * w * h + y * w + x] = c[k];
            }
            depth[y * w + x] = *d;
        }
    }
    (img, depth)
}

/// The camera loop: radius and elevation jittered per scene and per view, looking at the scene centre.
fn camera_loop(rng: &mut impl Rng, n: usize, width: u32, height: u32) -> Vec<Camera> {
    let hfov = rng.gen_range(50f64..70.0).to_radians();
    let fx = width as f64 / (2.0 * (hfov / 2.0).tan());
    let tpl = Camera {
        fx,
        fy: fx,
        cx: width as f64 / 2.0,
        cy: height as f64 / 2.0,
        width,
        height,
        c2w: [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
    };
    let radius = rng.gen_range(8.0..11.0);
    let elev = rng.gen_range(10f64..35.0).to_radians();
    let phase = rng.gen_range(0.0..std::f64::consts::TAU);
    let centre = V3::new(0.0, -rng.gen_range(0.3..1.0), 0.0);
    let up = V3::new(0.0, -1.0, 0.0);
    (0..n)
        .map(|i| {
            let a = phase + std::f64::consts::TAU * i as f64 / n as f64;
            let e = elev + rng.gen_range(-0.05..0.05);
            let rr = radius * rng.gen_range(0.95..1.05);
            let eye = centre + V3::new(rr * e.cos() * a.cos(), -rr * e.sin(), rr * e.cos() * a.sin());
            let look = centre + V3::new(rng.gen_range(-0.3..0.3), rng.gen_range(-0.2..0.2), rng.gen_range(-0.3..0.3));
            trajectory::look_at(&tpl, &eye, &look, &up)
        })
        .collect()
}

/// Scene `seed`: its world, camera loop and renders.
pub fn generate(seed: u64, opts: &GenOptions) -> GenScene {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0x5EED_0F5C_E7E5);
    let world = build_world(&mut rng);
    let cams = camera_loop(&mut rng, opts.views, opts.width, opts.height);
    let views = cams
        .into_iter()
        .map(|c| {
            let (image, depth) = render_view(&world, &c, opts.samples);
            GenView { image, depth, camera: c }
        })
        .collect();
    GenScene { name: format!("procedural-{seed}"), views, near: 1.0, far: 100.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> GenOptions {
        GenOptions { views: 6, width: 64, height: 32, samples: 1 }
    }

    #[test]
    fn deterministic_finite_and_varied() {
        let a = generate(11, &small());
        let b = generate(11, &small());
        let c = generate(12, &small());
        assert_eq!(a.views.len(), 6);
        for (x, y) in a.views.iter().zip(&b.views) {
            assert_eq!(x.image, y.image);
            assert_eq!(x.camera, y.camera);
        }
        assert!(a.views.iter().all(|v| v.image.iter().all(|p| p.is_finite() && (0.0..=1.0).contains(p))));
        assert_ne!(a.views[0].image, c.views[0].image);
        assert_ne!(a.views[0].image, a.views[1].image);
        // Cameras ≈ 10 units from the look-at point.
        let d = mvsplat360_pipeline_free_look_at_distance(&a.views.iter().map(|v| v.camera.clone()).collect::<Vec<_>>());
        assert!((7.0..12.0).contains(&d), "{d}");
    }

    fn mvsplat360_pipeline_free_look_at_distance(cams: &[Camera]) -> f64 {
        let p = trajectory::look_at_point(cams);
        cams.iter().map(|c| (c.center() - p).norm()).sum::<f64>() / cams.len() as f64
    }

    /// A lone bright sphere under a dark sky: its image centroid is where the camera model projects its centre
    /// (within 1 px; the sphere is small, so perspective shifts the silhouette centroid by far less).
    #[test]
    fn sphere_projects_where_the_camera_says() {
        let c = V3::new(0.7, -0.8, -0.4);
        let world = World {
            objects: vec![Object {
                shape: Shape::Sphere { c, r: 0.25 },
                mat: Material { a: V3::repeat(1.0), b: V3::repeat(1.0), pattern: Pattern::Checker(1.0), seed: 0 },
            }],
            ground: Material { a: V3::zeros(), b: V3::zeros(), pattern: Pattern::Checker(1.0), seed: 0 },
            light: V3::new(0.0, -1.0, 0.0),
            sky_top: V3::zeros(),
            sky_horizon: V3::zeros(),
            ambient: 1.0,
        };
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let cams = camera_loop(&mut rng, 5, 160, 96);
        for cam in &cams {
            let (img, _) = render_view(&world, cam, 3);
            let (w, h) = (160usize, 96usize);
            let (mut sx, mut sy, mut sw) = (0.0, 0.0, 0.0);
            for y in 0..h {
                for x in 0..w {
                    let v = img[y * w + x] as f64;
                    sx += v * (x as f64 + 0.5);
                    sy += v * (y as f64 + 0.5);
                    sw += v;
                }
            }
            assert!(sw > 5.0, "sphere not visible");
            let (u, v, _) = cam.project(&c);
            let (cx, cy) = (sx / sw, sy / sw);
            assert!((cx - u).abs() < 1.0 && (cy - v).abs() < 1.0, "centroid ({cx:.2},{cy:.2}) vs projection ({u:.2},{v:.2})");
        }
    }

    /// Depth is the distance along the pixel centre's ray to the first surface: for a lone sphere on the
    /// ground, every finite depth puts the point on the sphere (|p − c| = r) or on the ground (y = 0), the
    /// sky's rays miss both, and the sphere's pixels are nearer than the ground behind them would be.
    #[test]
    fn depth_is_the_ray_distance_to_the_first_surface() {
        let (c, r) = (V3::new(0.3, -0.9, 0.2), 0.9);
        let plain = Material { a: V3::repeat(0.5), b: V3::repeat(0.5), pattern: Pattern::Checker(1.0), seed: 0 };
        let world = World {
            objects: vec![Object { shape: Shape::Sphere { c, r }, mat: plain }],
            ground: plain,
            light: V3::new(0.0, -1.0, 0.0),
            sky_top: V3::zeros(),
            sky_horizon: V3::zeros(),
            ambient: 1.0,
        };
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let mut cams = camera_loop(&mut rng, 3, 64, 32);
        // The loop looks down on the ground; a level camera also sees the sky.
        cams.push(trajectory::look_at(&cams[0], &V3::new(8.0, -1.5, 0.5), &V3::new(0.0, -1.5, 0.0), &V3::new(0.0, -1.0, 0.0)));
        let (mut on_sphere, mut on_ground, mut sky) = (0, 0, 0);
        for cam in &cams {
            let (_, depth) = render_view(&world, cam, 1);
            let (o, rot) = (cam.center(), cam.rotation());
            for y in 0..32 {
                for x in 0..64 {
                    let d = (rot * V3::new((x as f64 + 0.5 - cam.cx) / cam.fx, (y as f64 + 0.5 - cam.cy) / cam.fy, 1.0)).normalize();
                    let t = depth[y * 64 + x] as f64;
                    // Closed forms of the two surfaces along this ray.
                    let oc = o - c;
                    let (b, cc) = (oc.dot(&d), oc.norm_squared() - r * r);
                    let t_sphere = (b * b - cc >= 0.0).then(|| -b - (b * b - cc).sqrt()).filter(|&t| t > 0.0);
                    let t_ground = (d.y > 0.0).then(|| -o.y / d.y);
                    let want = match (t_sphere, t_ground) {
                        (Some(a), Some(g)) => Some(a.min(g)),
                        (a, g) => a.or(g),
                    };
                    match want {
                        None => {
                            assert!(t.is_infinite(), "pixel ({x},{y}) sees the sky but has depth {t}");
                            sky += 1;
                        }
                        Some(w) => {
                            assert!((t - w).abs() <= 1e-4 * w, "pixel ({x},{y}): depth {t}, closed form {w}");
                            let p = o + d * t;
                            if ((p - c).norm() - r).abs() < 1e-3 {
                                on_sphere += 1;
                            } else {
                                assert!(p.y.abs() < 1e-3, "pixel ({x},{y}): point {p:?} on neither surface");
                                on_ground += 1;
                            }
                        }
                    }
                }
            }
        }
        assert!(on_sphere > 50 && on_ground > 50 && sky > 50, "sphere {on_sphere}, ground {on_ground}, sky {sky}");
    }
}
