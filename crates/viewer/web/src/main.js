// The `mvsplat360 view` page: 3D Gaussians (Spark on three.js), the video, a frame comparison and the run's
// settings. Everything it reads is listed in `manifest.json` (written by the server or `view --static`), so the
// page never asks for a file that is not there and the parts without data stay hidden.
import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";
import {
  KCamera,
  applyOpenCVCamera,
  lookAtPoint,
  projectWithThree,
  threeMatrixFromOpenCV,
  worldUp,
} from "./cameras.js";

const $ = (id) => document.getElementById(id);
const KINDS = ["gsplat", "refined", "final", "gt"];
const KIND_LABEL = { gsplat: "3DGS (gsplat)", refined: "refined", final: "final", gt: "ground truth" };

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

async function getJSON(path) {
  const r = await fetch(path);
  if (!r.ok) throw new Error(`${path}: HTTP ${r.status}`);
  return r.json();
}

function nextFrame() {
  return new Promise((resolve) => requestAnimationFrame(() => resolve()));
}

// Milliseconds since navigation at each loading step (shown to the browser test and in the console).
const timings = {};
const mark = (what) => {
  timings[what] = Math.round(performance.now());
};

// The loading line of the 3D panel. Each state change is logged (state, ms since navigation, text shown) in
// `mvsplat360.status` so the browser test can check the order; progress updates within a state are not logged.
const statusLog = [];
function setStatus(state, text, extra = {}) {
  const line = $("status3d");
  line.hidden = state === "done" || state === "failed" || state === "no-webgl2";
  $("status3d-text").textContent = text;
  $("status3d-bar").hidden = true;
  statusLog.push({ state, ms: Math.round(performance.now()), text, ...extra });
}

const fmtBytes = (n) => (n < 1e6 ? `${Math.round(n / 1e3)} kB` : `${(n / 1e6).toFixed(1)} MB`);

// Reads a response body chunk by chunk to show how much has arrived. The total is Content-Length when the server
// sends one and the body is not compressed in transit (then the length counts other bytes than the reader's).
async function readWithProgress(resp, onProgress) {
  const len = Number(resp.headers.get("Content-Length"));
  const total = len > 0 && !resp.headers.get("Content-Encoding") ? len : null;
  if (!resp.body) return { bytes: new Uint8Array(await resp.arrayBuffer()), total };
  const reader = resp.body.getReader();
  const chunks = [];
  let received = 0;
  for (;;) {
    const { done, value } = await reader.read();
    if (done) break;
    chunks.push(value);
    received += value.length;
    onProgress(received, total);
  }
  const bytes = new Uint8Array(received);
  let at = 0;
  for (const c of chunks) {
    bytes.set(c, at);
    at += c.length;
  }
  return { bytes, total };
}

// WebGL2 on the page's own canvas, with the attributes three.js asks for, so that its getContext call returns
// this very context. Null where the browser has none (too old, hardware acceleration off, GPU blocklisted): that
// is the answer to trust, not the presence of WebGL2RenderingContext.
function webgl2(canvas) {
  try {
    return canvas.getContext("webgl2", { alpha: true, depth: true, stencil: false, antialias: false });
  } catch {
    return null;
  }
}

const fmt = (v) => (typeof v === "number" ? (Number.isInteger(v) ? String(v) : v.toPrecision(4)) : JSON.stringify(v));

// ---------------------------------------------------------------------------------------------------- run info
function showRun(run, metrics) {
  $("title").textContent = `${run.scene_name ?? "render"} — mvsplat360 view`;
  document.title = $("title").textContent;
  const info = $("info");
  const rows = [
    ["scene", run.scene],
    ["model", run.model],
    ["experiment", run.experiment],
    ["frames", run.frames],
    ["Gaussians", run.gaussians],
    ["peak memory (MiB)", run.peak_mib],
    ["version", run.version],
  ];
  for (const [k, v] of Object.entries(run.settings ?? {})) rows.push([k, v]);
  const table = el("table", { class: "kv" });
  for (const [k, v] of rows) {
    if (v === undefined || v === null) continue;
    table.append(el("tr", {}, el("th", {}, k), el("td", {}, typeof v === "string" ? v : fmt(v))));
  }
  info.append(el("h3", {}, "Settings"), table);

  const times = Object.entries(run.stage_seconds ?? {});
  if (times.length) {
    const total = run.stage_seconds.total ?? Math.max(...times.map(([, s]) => s));
    const t = el("table", { class: "kv times" });
    for (const [k, s] of times) {
      const bar = el("div", { class: "bar" });
      bar.style.width = `${Math.max(1, (100 * s) / (total || 1))}%`;
      t.append(el("tr", {}, el("th", {}, k), el("td", {}, `${s.toFixed(2)} s`), el("td", { class: "barcell" }, bar)));
    }
    info.append(el("h3", {}, "Stage times"), t);
  }

  const m = metrics ?? run.metrics;
  if (m) {
    // metrics.json scores the frames named by `frames`: "refined" (the paper's figures) with the histogram-matched
    // final frames nested under "final", or "final" alone without a refiner. Files from before the `frames` key
    // scored the final frames.
    const sets = [[m.frames ?? "final", m]];
    if (m.final && typeof m.final === "object") sets.push([m.final.frames ?? "final", m.final]);
    const keys = ["psnr", "ssim", "lpips", "dists", "fid"];
    const t = el("table", { class: "kv", id: "metrics-table" });
    t.append(el("thead", {}, el("tr", {}, el("th", {}), ...keys.map((k) => el("th", {}, k.toUpperCase())))));
    const body = el("tbody");
    for (const [frames, row] of sets) {
      const cells = keys.map((k) => el("td", {}, row[k] === null || row[k] === undefined ? "—" : fmt(row[k])));
      body.append(el("tr", {}, el("th", {}, `${frames} vs ground truth`), ...cells));
    }
    t.append(body);
    info.append(el("h3", {}, "Metrics"), t);
    // FID conventions give different numbers (`render --fid-variant`): say whose this is.
    const fid = sets.find(([, row]) => typeof row.fid === "number" && row.fid_variant);
    if (fid) info.append(el("div", { class: "hint" }, `FID as ${fid[1].fid_variant} computes it`));
  }
}

// ------------------------------------------------------------------------------------------------------ 3D view
async function show3D(manifest, camerasJson, run) {
  const cams = camerasJson.cameras;
  const targets = cams.filter((c) => c.role === "target");
  const contexts = cams.filter((c) => c.role === "context");
  const first = targets[0] ?? cams[0];
  const [w, h] = [first.width, first.height];
  const near = run.settings?.near ?? 0.01;
  const far = run.settings?.far ?? 1000;

  const box = $("view3d");
  const canvas = $("canvas3d");
  // Spark needs WebGL2: without it, say so and leave the rest of the page working (and fetch no Gaussians).
  if (!webgl2(canvas)) {
    setStatus("no-webgl2", "");
    $("no-webgl2").hidden = false;
    return null;
  }
  // The canvas keeps the images' aspect so the view from a camera frames exactly what its photo shows.
  const cssW = Math.min(Math.max(box.parentElement.clientWidth - 24, 320), 960);
  const cssH = Math.round((cssW * h) / w);
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: false });
  // Resolution of the 3D view relative to the screen (`?res=0.25` sets it): every splat is blended over its whole
  // footprint, so a lower one keeps large splats fast on weak or software GL.
  const resSel = $("res");
  const resParam = Number(new URLSearchParams(location.search).get("res"));
  if (resParam > 0 && resParam <= 1) {
    if (![...resSel.options].some((o) => Number(o.value) === resParam)) resSel.append(el("option", { value: String(resParam) }, `${resParam}×`));
    resSel.value = String(resParam);
  }
  const setRes = () => {
    renderer.setPixelRatio((window.devicePixelRatio || 1) * Number(resSel.value));
    renderer.setSize(cssW, cssH);
  };
  setRes();
  renderer.setClearColor(0x000000, 1);

  const scene = new THREE.Scene();
  // Our rasterizer (as the official diff-gaussian-rasterization) adds 0.3 px² to every 2D covariance without
  // opacity compensation: that is Spark's preBlurAmount, not its blurAmount.
  const spark = new SparkRenderer({ renderer, preBlurAmount: 0.3, blurAmount: 0.0 });
  scene.add(spark);

  const camera = new KCamera(50, w / h, near, far);
  camera.up.copy(worldUp(cams));
  const center = lookAtPoint(cams);

  const plyUrl = manifest.data + manifest.files.gaussians;
  setStatus("fetching", "fetching Gaussians…");
  const resp = await fetch(plyUrl);
  if (!resp.ok) throw new Error(`${plyUrl}: HTTP ${resp.status}`);
  const bar = $("status3d-bar");
  const { bytes, total } = await readWithProgress(resp, (received, total) => {
    $("status3d-text").textContent = `fetching Gaussians… ${fmtBytes(received)}${total ? ` of ${fmtBytes(total)}` : ""}`;
    bar.hidden = !total;
    if (total) bar.value = Math.min(received / total, 1);
  });
  mark("ply fetched");
  setStatus("decoding", `decoding ${fmtBytes(bytes.length)} of Gaussians…`, { bytes: bytes.length, total });
  // Spark decodes in a worker, so the line above is painted while it works.
  const splats = new SplatMesh({ fileBytes: bytes, fileType: "ply" });
  await splats.initialized;
  mark("splats decoded");
  scene.add(splats);

  // OrbitControls takes its orbit axis from camera.up when constructed.
  const controls = new OrbitControls(camera, canvas);
  controls.enableDamping = false;

  let renderUntil = 0;
  let framesRendered = 0;
  const kick = (ms = 800) => {
    renderUntil = Math.max(renderUntil, performance.now() + ms);
  };
  // Render on demand (a burst after every change: Spark sorts in a worker, a few frames late), not 60 fps forever.
  // A new frame only once the GPU finished the last one (a fence): otherwise a slow (software) GL queues frames
  // faster than it draws them and the page stops responding until the queue drains.
  const gl = renderer.getContext();
  const frameTimes = [];
  let pending = null;
  renderer.setAnimationLoop(() => {
    if (pending) {
      if (gl.clientWaitSync(pending.fence, 0, 0) === gl.TIMEOUT_EXPIRED) return;
      gl.deleteSync(pending.fence);
      frameTimes.push(Math.round(performance.now() - pending.t));
      if (frameTimes.length > 20) frameTimes.shift();
      pending = null;
      framesRendered++;
    }
    if (performance.now() < renderUntil) {
      const t = performance.now();
      renderer.render(scene, camera);
      pending = { t, fence: gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0) };
      gl.flush();
    }
  });
  controls.addEventListener("change", () => kick());
  resSel.addEventListener("change", () => {
    setRes();
    kick();
  });

  const label = $("view-label");
  function setView(role, k) {
    const list = role === "context" ? contexts : targets;
    const cam = list[k];
    if (!cam) throw new Error(`no ${role} camera ${k}`);
    applyOpenCVCamera(camera, cam);
    // Orbit about the rig's look-at point, projected on this camera's optical axis, so the view does not jump.
    const fwd = new THREE.Vector3(cam.c2w[0][2], cam.c2w[1][2], cam.c2w[2][2]);
    const depth = Math.max(center.clone().sub(camera.position).dot(fwd), near);
    controls.target.copy(camera.position).addScaledVector(fwd, depth);
    label.textContent = `${role} ${k}${cam.name ? ` (${cam.name})` : ""}`;
    for (const b of document.querySelectorAll("#cam-buttons button")) {
      b.classList.toggle("active", b.dataset.role === role && Number(b.dataset.k) === k);
    }
    kick(1500);
  }

  const buttons = $("cam-buttons");
  const group = (role, list) => {
    if (!list.length) return;
    const g = el("div", { class: "btn-group" }, el("span", { class: "group-label" }, `${role}:`));
    list.forEach((c, k) => {
      const b = el("button", { title: c.name ?? `${role} ${k}`, onclick: () => setView(role, k) }, String(k));
      b.dataset.role = role;
      b.dataset.k = String(k);
      g.append(b);
    });
    buttons.append(g);
  };
  group("target", targets);
  group("context", contexts);

  setView(targets.length ? "target" : "context", 0);
  // Wait until frames have been drawn after the sort settled (Spark sorts asynchronously).
  // Keeps rendering while it waits: on a slow (software) GL a frame can take longer than a kick lasts.
  const settle = async (ms = 1200) => {
    const start = framesRendered;
    const t0 = performance.now();
    while (performance.now() - t0 < ms || framesRendered - start < 3) {
      kick(300);
      await nextFrame();
    }
  };
  $("view3d").hidden = false;
  const n = splats.numSplats ?? splats.packedSplats?.numSplats;
  setStatus("sorting", `sorting ${n ? `${n.toLocaleString("en")} ` : ""}splats, drawing the first frames…`);
  await settle();
  mark("settled");
  setStatus("done", "");
  return {
    setView,
    settle,
    // The canvas as a PNG data URL, rendered now (the drawing buffer is only valid within this task).
    snapshot() {
      renderer.render(scene, camera);
      return canvas.toDataURL("image/png");
    },
    numSplats: () => splats.numSplats ?? splats.packedSplats?.numSplats,
    // Milliseconds the last rendered frames took on the main thread (software GL makes them long).
    frameTimes,
  };
}

// ---------------------------------------------------------------------------------------------- video + frames
function showVideo(manifest) {
  const vids = ["video", "compare"].filter((k) => manifest.files[k]);
  if (!vids.length) return;
  const video = $("video");
  const pick = $("video-pick");
  for (const k of vids) pick.append(el("option", { value: k }, k === "video" ? "final video" : "comparison video"));
  const load = () => {
    video.src = manifest.data + manifest.files[pick.value];
  };
  pick.addEventListener("change", load);
  pick.hidden = vids.length < 2;
  load();
  $("video-section").hidden = false;
}

function showFrames(manifest) {
  const kinds = KINDS.filter((k) => (manifest.frames[k] ?? []).length);
  const n = Math.max(0, ...kinds.map((k) => manifest.frames[k].length));
  if (!kinds.length || !n) return null;
  const has = Object.fromEntries(kinds.map((k) => [k, new Set(manifest.frames[k])]));
  const name = (i) => `${String(i).padStart(4, "0")}.png`;
  const src = (k, i) => (has[k].has(name(i)) ? `${manifest.data}frames/${k}/${name(i)}` : null);

  const slider = $("frame");
  slider.max = String(n - 1);
  const grid = $("frames-grid");
  const imgs = {};
  for (const k of kinds) {
    imgs[k] = el("img", { alt: KIND_LABEL[k] });
    grid.append(el("figure", {}, imgs[k], el("figcaption", {}, KIND_LABEL[k])));
  }
  const wipeA = $("wipe-a");
  const wipeB = $("wipe-b");
  for (const sel of [wipeA, wipeB]) for (const k of kinds) sel.append(el("option", { value: k }, KIND_LABEL[k]));
  wipeA.value = kinds[0];
  wipeB.value = kinds.includes("gt") ? "gt" : kinds[kinds.length - 1];

  const setSrc = (img, s) => {
    if (s) {
      img.src = s;
      img.style.visibility = "visible";
    } else {
      img.removeAttribute("src");
      img.style.visibility = "hidden";
    }
  };
  const update = () => {
    const i = Number(slider.value);
    $("frame-label").textContent = `frame ${i} / ${n - 1}`;
    for (const k of kinds) setSrc(imgs[k], src(k, i));
    setSrc($("wipe-img-a"), src(wipeA.value, i));
    setSrc($("wipe-img-b"), src(wipeB.value, i));
    $("wipe-img-b").style.clipPath = `inset(0 0 0 ${$("wipe").value}%)`;
  };
  const mode = $("frame-mode");
  const setMode = () => {
    const wipe = mode.value === "wipe";
    $("frames-grid").hidden = wipe;
    $("wipe-box").hidden = !wipe;
    $("wipe-controls").hidden = !wipe;
  };
  for (const e of [slider, $("wipe"), wipeA, wipeB]) e.addEventListener("input", update);
  mode.addEventListener("change", setMode);
  update();
  setMode();
  $("frames-section").hidden = false;
  return { count: n, kinds, slider };
}

// ---------------------------------------------------------------------------------------------------------- main
async function main() {
  const t0 = performance.now();
  const api = { ready: false, timings, status: statusLog, cvToThree: { threeMatrixFromOpenCV, projectWithThree } };
  window.mvsplat360 = api;
  const manifest = await getJSON("manifest.json");
  const [camerasJson, run, metrics] = await Promise.all([
    getJSON(manifest.data + manifest.files.cameras),
    getJSON(manifest.data + manifest.files.run),
    manifest.files.metrics ? getJSON(manifest.data + manifest.files.metrics) : null,
  ]);
  api.cameras = camerasJson.cameras;
  showRun(run, metrics);
  showVideo(manifest);
  api.frames = showFrames(manifest);
  const view = await show3D(manifest, camerasJson, run);
  api.webgl2 = view !== null;
  Object.assign(api, view);
  const targets = camerasJson.cameras.filter((c) => c.role === "target").length;
  const to3D = $("frame-3d");
  if (view && api.frames && targets === api.frames.count) {
    to3D.addEventListener("click", () => {
      api.setView("target", Number(api.frames.slider.value));
      $("view3d").scrollIntoView({ behavior: "smooth" });
    });
  } else {
    to3D.hidden = true;
  }
  api.loadMs = performance.now() - t0;
  api.timings = timings;
  api.ready = true;
  document.body.dataset.ready = "1";
}

window.mvsplat360Ready = main().catch((e) => {
  setStatus("failed", "");
  const box = $("error");
  box.textContent = `Could not show this render: ${e.message ?? e}`;
  box.hidden = false;
  console.error(e);
  throw e;
});
