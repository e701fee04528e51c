// The one place where `cameras.json` (OpenCV: x right, y down, z forward; c2w + K in pixels) becomes three.js
// (camera looks down -z with y up). Everything else in the page works with the results of these functions.
import * as THREE from "three";

// OpenCV camera axes → three.js camera axes: flip y and z (a rotation of π about x), so
// c2w_three = c2w_cv · diag(1, -1, -1, 1).
export function threeMatrixFromOpenCV(c2w) {
  const m = new THREE.Matrix4();
  m.set(
    c2w[0][0], -c2w[0][1], -c2w[0][2], c2w[0][3],
    c2w[1][0], -c2w[1][1], -c2w[1][2], c2w[1][3],
    c2w[2][0], -c2w[2][1], -c2w[2][2], c2w[2][3],
    0, 0, 0, 1,
  );
  return m;
}

// Projection from pixel intrinsics (the principal point need not be centred), OpenGL clip space:
// pixel u = fx·x/z + cx maps to NDC 2u/W − 1, and v (down) to 1 − 2v/H.
export function projectionFromK(K, width, height, near, far) {
  const [fx, cx] = [K[0][0], K[0][2]];
  const [fy, cy] = [K[1][1], K[1][2]];
  const m = new THREE.Matrix4();
  m.set(
    (2 * fx) / width, 0, 1 - (2 * cx) / width, 0,
    0, (2 * fy) / height, (2 * cy) / height - 1, 0,
    0, 0, -(far + near) / (far - near), (-2 * far * near) / (far - near),
    0, 0, -1, 0,
  );
  return m;
}

// A PerspectiveCamera whose projection comes from K when one is set (OrbitControls and resizes call
// updateProjectionMatrix, which must keep the intrinsics).
export class KCamera extends THREE.PerspectiveCamera {
  setIntrinsics(K, width, height) {
    this.K = K;
    this.imageSize = [width, height];
    this.aspect = width / height;
    this.fov = THREE.MathUtils.radToDeg(2 * Math.atan(height / 2 / K[1][1]));
    this.updateProjectionMatrix();
  }

  updateProjectionMatrix() {
    if (!this.K) {
      super.updateProjectionMatrix();
      return;
    }
    const [w, h] = this.imageSize;
    this.projectionMatrix.copy(projectionFromK(this.K, w, h, this.near, this.far));
    this.projectionMatrixInverse.copy(this.projectionMatrix).invert();
  }
}

// Put `camera` at an OpenCV camera: pose from c2w, projection from K.
export function applyOpenCVCamera(camera, cam) {
  const m = threeMatrixFromOpenCV(cam.c2w);
  m.decompose(camera.position, camera.quaternion, camera.scale);
  camera.setIntrinsics(cam.K, cam.width, cam.height);
  camera.updateMatrixWorld(true);
}

// The world point nearest to every optical axis (least squares): what the cameras look at, the orbit centre.
export function lookAtPoint(cams) {
  const A = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
  const b = [0, 0, 0];
  for (const c of cams) {
    const o = [c.c2w[0][3], c.c2w[1][3], c.c2w[2][3]];
    const d = [c.c2w[0][2], c.c2w[1][2], c.c2w[2][2]];
    for (let i = 0; i < 3; i++) {
      for (let j = 0; j < 3; j++) {
        const p = (i === j ? 1 : 0) - d[i] * d[j];
        A[i][j] += p;
        b[i] += p * o[j];
      }
    }
  }
  const m = new THREE.Matrix3().set(...A[0], ...A[1], ...A[2]);
  if (Math.abs(m.determinant()) < 1e-9) {
    // Parallel axes (a forward-facing rig): fall back to a point in front of the first camera.
    const c = cams[0].c2w;
    return new THREE.Vector3(c[0][3] + c[0][2], c[1][3] + c[1][2], c[2][3] + c[2][2]);
  }
  return new THREE.Vector3(...b).applyMatrix3(m.invert());
}

// The world "up" of a rig: OpenCV's y points down in every camera, so up is the mean of −y axes.
export function worldUp(cams) {
  const u = new THREE.Vector3();
  for (const c of cams) u.add(new THREE.Vector3(-c.c2w[0][1], -c.c2w[1][1], -c.c2w[2][1]));
  return u.lengthSq() > 0 ? u.normalize() : new THREE.Vector3(0, 1, 0);
}

// Pixel coordinates of world point `p` seen by OpenCV camera `cam`, computed the three.js way (pose + projection
// above). Exposed so the browser test can check the conversion against the plain pinhole formula.
export function projectWithThree(cam, p, near = 0.01, far = 1000) {
  const view = threeMatrixFromOpenCV(cam.c2w).invert();
  const proj = projectionFromK(cam.K, cam.width, cam.height, near, far);
  const v = new THREE.Vector4(p[0], p[1], p[2], 1).applyMatrix4(view).applyMatrix4(proj);
  const [x, y] = [v.x / v.w, v.y / v.w];
  return [((x + 1) / 2) * cam.width, ((1 - y) / 2) * cam.height];
}
