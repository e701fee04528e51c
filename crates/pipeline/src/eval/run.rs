//! The evaluation's run: the scenes selected from the index, resumed from disk, claimed and rendered under
//! leases, and the tables written from every scene's record.

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::Device;
use mvsplat360_dataset::torch_chunk::ChunkScene;
use mvsplat360_dataset::EvaluationEntry;
use serde_json::json;

use super::lease::{Claim, Counted, Leases};
use super::report::*;
use super::score::*;
use super::*;

/// The scenes of the index this run takes.
struct Selection {
    plans: Vec<ScenePlan>,
    /// In the index, absent from the data.
    missing: Vec<String>,
    null_entries: usize,
    /// Non-null scenes selected (planned + missing).
    selected: usize,
}

/// What became of each scene so far.
struct Tally {
    records: Vec<Option<SceneRecord>>,
    resumed: Vec<String>,
    rescored: Vec<String>,
    rendered: Vec<String>,
    failed: Vec<(String, String)>,
    missing: Vec<String>,
    warnings: Vec<String>,
}

/// The run's fixed facts beside [`Ctx`], for the tables.
struct RunInfo {
    t_all: Instant,
    data_dir: PathBuf,
    settings: serde_json::Value,
    selected: usize,
    null_entries: usize,
    /// Warnings already shown before rendering.
    n_warned: usize,
}

/// Flags checked before any work.
fn check_request(req: &EvalRequest, spec: &crate::model::ModelSpec, index: &BTreeMap<String, Option<EvaluationEntry>>) -> Result<()> {
    if req.refine.window == 0 {
        return Err(flag("--window", "must be at least 1"));
    }
    if req.refine.vae_chunk == 0 {
        return Err(flag("--vae-chunk", "must be at least 1"));
    }
    if spec.refiner.is_some() && req.refine.steps == 0 {
        return Err(flag("--steps", "must be at least 1 (or use --refiner none)"));
    }
    for (name, list) in [("--scenes", req.scenes.as_deref().unwrap_or(&[])), ("--exclude", &req.exclude[..])] {
        if let Some(k) = list.iter().find(|k| !index.contains_key(*k)) {
            return Err(flag(name, format!("no scene `{k}` in {}", req.index.display())));
        }
    }
    Ok(())
}

fn select_scenes(req: &EvalRequest, index: &BTreeMap<String, Option<EvaluationEntry>>, chunk_of: &HashMap<String, String>) -> Selection {
    let wanted: Option<BTreeSet<&String>> = req.scenes.as_ref().map(|l| l.iter().collect());
    let excluded: BTreeSet<&String> = req.exclude.iter().collect();
    let (mut plans, mut missing, mut null_entries) = (Vec::new(), Vec::new(), 0);
    for (k, e) in index {
        if wanted.as_ref().is_some_and(|w| !w.contains(k)) || excluded.contains(k) {
            continue;
        }
        let Some(e) = e else {
            null_entries += 1;
            continue;
        };
        if req.limit.is_some_and(|l| plans.len() + missing.len() >= l) {
            break;
        }
        match chunk_of.get(k) {
            Some(c) => plans.push(ScenePlan::new(k, c, e)),
            None => missing.push(k.clone()),
        }
    }
    let selected = plans.len() + missing.len();
    Selection { plans, missing, null_entries, selected }
}

/// The settings recorded in `eval.json`; a merge keeps the records' precision, whatever the command asks for.
fn run_settings(req: &EvalRequest, spec: &crate::model::ModelSpec, size: InputSize) -> serde_json::Value {
    let mut settings = settings_json(req, spec, size);
    if req.merge_only {
        let stored: Option<serde_json::Value> = std::fs::read_to_string(req.out.join(SETTINGS_JSON)).ok().and_then(|t| serde_json::from_str(&t).ok());
        for key in ["refiner_dtype", "encoder_dtype"] {
            match stored.as_ref().and_then(|v| v.get(key)) {
                Some(d) => settings[key] = d.clone(),
                None => {
                    settings.as_object_mut().map(|o| o.remove(key));
                }
            }
        }
    }
    settings
}

fn read_noise(req: &EvalRequest, plans: &[ScenePlan]) -> Result<Option<HashMap<String, Tensor>>> {
    let Some(f) = &req.noise else { return Ok(None) };
    let m = candle_core::safetensors::load(f, &Device::Cpu).map_err(|e| flag("--noise", format!("{}: {e}", f.display())))?;
    if let Some(p) = plans.iter().find(|p| !m.contains_key(&p.key)) {
        return Err(flag("--noise", format!("{} has no noise for scene `{}`: it needs one tensor per evaluated scene", f.display(), p.key)));
    }
    Ok(Some(m))
}

pub(super) fn run_scenes(req: &EvalRequest, progress: &dyn Progress) -> Result<EvalSummary> {
    let t_all = Instant::now();
    let index = mvsplat360_dataset::read_evaluation_index(&req.index)?;
    let (data_dir, chunk_of) = chunk_map(&req.data, progress)?;
    let spec = crate::model::resolve(&req.model)?;
    check_request(req, &spec, &index)?;
    let sel = select_scenes(req, &index, &chunk_of);
    let mut warnings = Vec::new();
    if !sel.missing.is_empty() {
        warnings.push(format!(
            "{} scene(s) of the index are not in {}: {}{}",
            sel.missing.len(),
            data_dir.display(),
            sel.missing.iter().take(5).cloned().collect::<Vec<_>>().join(", "),
            if sel.missing.len() > 5 { ", …" } else { "" }
        ));
    }
    let out = &req.out;
    output::check_writable(out, "--out")?;
    output::remove_partials(out);
    let size = req.size.unwrap_or(InputSize::Fixed { width: spec.data.image_width, height: spec.data.image_height });
    let settings = run_settings(req, &spec, size);
    check_settings(out, &settings)?;
    // A merge renders nothing: an official checkpoint's refiner is not converted for it.
    let refine_file = match &spec.refiner {
        Some((_, w)) if !req.merge_only => Some(crate::model::refiner_safetensors(w, &|m| progress.note(m))?),
        _ => None,
    };
    let methods: Vec<Method> = if spec.refiner.is_some() { Method::ALL.to_vec() } else { vec![Method::GSplat] };
    let nets = load_nets(req, &mut warnings)?;
    for w in &warnings {
        progress.note(&format!("warning: {w}"));
    }
    for d in std::iter::once(GT_DIR).chain(methods.iter().map(|m| m.dir())).chain([SCENES_DIR]) {
        output::create_dir(&out.join(d))?;
    }
    let device = if req.merge_only { Device::Cpu } else { req.model.compute.open()? };
    // `.torch` chunks come with no pose engine to state their units.
    let scene_scale = crate::scale::resolve(req.scene_scale, None, spec.scene_scale);
    let noise = read_noise(req, &sel.plans)?;
    let leases = Leases::with_timing(&out.join(SCENES_DIR), req.lease);
    // What the scenes' renders report moves this process's leases' progress.
    let counted = Counted { inner: progress, count: leases.progress_counter() };
    let pre = Preprocess { size, multiple: spec.encoder.image_multiple() as u32 };
    let info = RunInfo { t_all, data_dir, settings, selected: sel.selected, null_entries: sel.null_entries, n_warned: warnings.len() };
    let cx = Ctx { req, spec, pre, refine_file, device, methods, nets, scene_scale, noise, progress: &counted };
    let mut tally = Tally {
        records: vec![None; sel.plans.len()],
        resumed: Vec::new(),
        rescored: Vec::new(),
        rendered: Vec::new(),
        failed: Vec::new(),
        missing: sel.missing,
        warnings,
    };
    let mut to_render = resume_scenes(&cx, &sel.plans, &mut tally)?;
    let mut incomplete = Vec::new();
    if req.merge_only {
        // A recorded failure is a result; a scene without record or failure is not done yet.
        for i in to_render.drain(..) {
            match read_failure(out, &sel.plans[i].key) {
                Some(msg) => tally.failed.push((sel.plans[i].key.clone(), msg)),
                None => incomplete.push(sel.plans[i].key.clone()),
            }
        }
    }
    render_scenes(&cx, &info.data_dir, &sel.plans, to_render, &leases, &mut tally)?;
    drop(leases);
    if req.shard.is_some() || !incomplete.is_empty() {
        // A rank (its scenes' records are on disk; the launcher or the last rank aggregates), or an incomplete merge.
        let images = tally.records.iter().flatten().map(|r| r.scored.len()).sum();
        return Ok(summary(out, &info, tally, Vec::new(), images, Vec::new(), incomplete));
    }
    write_tables(&cx, &info, tally)
}

/// Complete scenes are kept, scenes with images but incomplete scores are re-scored from disk; returns the
/// positions of the scenes left to render, in this process's order.
fn resume_scenes(cx: &Ctx, plans: &[ScenePlan], tally: &mut Tally) -> Result<Vec<usize>> {
    let out = &cx.req.out;
    let used = cx.nets.used();
    let mut to_render = Vec::new();
    for i in scene_order(plans, cx.req.shard) {
        let plan = &plans[i];
        match resume_state(out, plan, &cx.methods, used) {
            Resume::Done(rec) => {
                tally.resumed.push(plan.key.clone());
                tally.records[i] = Some(*rec);
            }
            Resume::Rescore => {
                cx.progress.note(&format!("scene {}: re-scoring its saved images", plan.key));
                let path = scene_json(out, &plan.key);
                let text = std::fs::read_to_string(&path).map_err(|e| werr(&path, e))?;
                let mut rec: SceneRecord = serde_json::from_str(&text).map_err(|e| werr(&path, e))?;
                cx.progress.begin("scoring", 0);
                rec.methods = score_scene(out, plan, &cx.methods, &cx.nets)?;
                cx.progress.end();
                rec.networks = used;
                tally.records[i] = Some(write_record(out, &rec)?);
                tally.rescored.push(plan.key.clone());
            }
            Resume::Render => to_render.push(i),
        }
    }
    if !tally.resumed.is_empty() {
        cx.progress.note(&format!("resuming: {} of {} scenes already complete in {}", tally.resumed.len(), plans.len(), out.display()));
    }
    Ok(to_render)
}

/// Renders each scene under its lease (see [`lease`]), so that processes sharing --out render it once; scenes
/// another live process holds are waited for, and taken over when their owner dies, goes silent or stalls.
fn render_scenes(cx: &Ctx, data_dir: &Path, plans: &[ScenePlan], to_render: Vec<usize>, leases: &Leases, tally: &mut Tally) -> Result<()> {
    let out = &cx.req.out;
    let started = std::time::SystemTime::now();
    let total = to_render.len();
    let mut queue: VecDeque<usize> = to_render.into();
    let mut waiting: Vec<usize> = Vec::new();
    let mut told: BTreeSet<usize> = BTreeSet::new();
    let mut cache: Option<(String, HashMap<String, ChunkScene>)> = None;
    let mut done = 0;
    loop {
        let Some(i) = queue.pop_front() else {
            if waiting.is_empty() {
                return Ok(());
            }
            std::thread::sleep(std::time::Duration::from_millis(500));
            for i in std::mem::take(&mut waiting) {
                let key = &plans[i].key;
                if let Resume::Done(rec) = resume_state(out, &plans[i], &cx.methods, cx.nets.used()) {
                    tally.resumed.push(key.clone());
                    tally.records[i] = Some(*rec);
                } else if let Some(msg) = read_failure_since(out, key, started) {
                    tally.failed.push((key.clone(), msg));
                } else {
                    queue.push_back(i);
                }
            }
            continue;
        };
        let plan = &plans[i];
        if let Claim::Held(owner) = leases.claim(&plan.key).map_err(|e| werr(&out.join(SCENES_DIR), e))? {
            if told.insert(i) {
                let t = cx.req.lease;
                cx.progress.note(&format!(
                    "scene {}: being rendered by {owner}; waiting for it (taken over if that process dies, is silent for {} s or makes no progress for {} s)",
                    plan.key,
                    t.stale_after.as_secs(),
                    t.stall_after.as_secs()
                ));
            }
            waiting.push(i);
            continue;
        }
        // Finished by another process since it was looked at.
        if let Resume::Done(rec) = resume_state(out, plan, &cx.methods, cx.nets.used()) {
            leases.release(&plan.key);
            tally.resumed.push(plan.key.clone());
            tally.records[i] = Some(*rec);
            continue;
        }
        done += 1;
        cx.progress.note(&format!(
            "[{done}/{total}] scene {} ({} context, {} targets, {} scored)",
            plan.key,
            plan.context.len(),
            plan.targets.len(),
            plan.scored.len()
        ));
        let mine = || leases.still_mine(&plan.key);
        let result = render_claimed(cx, data_dir, plan, &mut cache, &mine, &mut tally.warnings);
        let failure = failure_json(out, &plan.key);
        match result {
            Ok(Rendered::Record(rec)) => {
                let _ = std::fs::remove_file(&failure);
                tally.rendered.push(plan.key.clone());
                tally.records[i] = Some(rec);
            }
            Ok(Rendered::NotInChunk) => {
                tally.warnings.push(format!(
                    "scene {} is listed in {} under {} but that chunk does not hold it",
                    plan.key,
                    data_dir.join("index.json").display(),
                    plan.chunk
                ));
                tally.missing.push(plan.key.clone());
            }
            Ok(Rendered::Lost) => {
                cx.progress.note(&format!(
                    "scene {}: another process took it over (this one was silent or made no progress for too long); dropped, nothing written",
                    plan.key
                ));
                // Its new owner's record is waited for like any scene another process holds.
                leases.release(&plan.key);
                waiting.push(i);
                continue;
            }
            Err(e) if is_data_error(&e) => {
                let msg = e.to_string();
                cx.progress.note(&format!("warning: scene {} failed, the others go on: {msg}", plan.key));
                let rec = json!({ "scene": plan.key, "error": msg, "host": mvsplat360_dataset::atomic::host_name(), "pid": std::process::id() });
                let written = if mine() { write_json(&failure, &rec) } else { Ok(()) };
                leases.release(&plan.key);
                written?;
                tally.failed.push((plan.key.clone(), msg));
                continue;
            }
            Err(e) => return Err(e),
        }
        leases.release(&plan.key);
    }
}

/// `metrics.json` and `metrics.md` from every scene's record.
fn write_tables(cx: &Ctx, info: &RunInfo, mut tally: Tally) -> Result<EvalSummary> {
    let (req, out, methods) = (cx.req, &cx.req.out, &cx.methods);
    let primary = methods[0];
    let done_records: Vec<&SceneRecord> = tally.records.iter().flatten().filter(|r| r.skipped.is_none()).collect();
    // One table, one precision: eval.json keeps processes of another --dtype out; this catches edited folders.
    let want = info.settings.get("refiner_dtype").and_then(|v| v.as_str()).unwrap_or("f32");
    let want_enc = info.settings.get("encoder_dtype").and_then(|v| v.as_str()).unwrap_or("f32");
    let mixed: Vec<String> = done_records
        .iter()
        .filter_map(|r| {
            r.rendered_by
                .as_ref()
                .filter(|b| b.refiner_dtype != want || b.encoder_dtype != want_enc)
                .map(|b| format!("{} (refiner {}, encoder {})", r.scene, b.refiner_dtype, b.encoder_dtype))
        })
        .collect();
    if !mixed.is_empty() {
        return Err(flag(
            "--out",
            format!(
                "{}: these scenes were rendered in another precision than the folder's (refiner {want}, encoder {want_enc}): {}; render them again (remove their scenes/*.json)",
                out.display(),
                mixed.join(", ")
            ),
        ));
    }
    let skipped_fov: Vec<String> = tally.records.iter().flatten().filter(|r| r.skipped.is_some()).map(|r| r.scene.clone()).collect();
    let mut table = Vec::new();
    for &m in methods {
        let imgs: Vec<&ImageScores> = done_records.iter().filter_map(|r| r.methods.get(m.key())).flatten().collect();
        let mut sc = method_scores(m, &imgs);
        if cx.nets.fid.is_some() {
            sc.fid = set_fid(out, &done_records, m, &mut tally.warnings)?;
        }
        table.push((m, sc));
    }
    let images = done_records.iter().map(|r| r.scored.len()).sum();
    let mut per_scene_json = serde_json::Map::new();
    let mut per_scene_primary = Vec::new();
    for r in &done_records {
        let mut o = serde_json::Map::new();
        o.insert("images".into(), json!(r.scored.len()));
        o.insert("gaussians".into(), json!(r.gaussians));
        for &m in methods {
            let imgs: Vec<&ImageScores> = r.methods.get(m.key()).map(|v| v.iter().collect()).unwrap_or_default();
            let sc = method_scores(m, &imgs);
            if m == primary {
                per_scene_primary.push((r.scene.clone(), sc.clone()));
            }
            o.insert(m.key().into(), json!({ "psnr": sc.psnr, "ssim": sc.ssim, "lpips": sc.lpips, "dists": sc.dists }));
        }
        per_scene_json.insert(r.scene.clone(), serde_json::Value::Object(o));
    }
    for w in &tally.warnings[info.n_warned..] {
        cx.progress.note(&format!("warning: {w}"));
    }
    let seconds = info.t_all.elapsed().as_secs_f64();
    let (rendered, rescored, resumed) = (&tally.rendered, &tally.rescored, &tally.resumed);
    let metrics = json!({
        "format": SETTINGS_FORMAT,
        "index": req.index.display().to_string(),
        "data": info.data_dir.display().to_string(),
        "model": cx.spec.description,
        "experiment": cx.spec.data.experiment,
        "settings": info.settings,
        "primary": primary.key(),
        "columns": ["psnr", "ssim", "lpips", "dists", "fid"],
        "fid_variant": req.fid_variant.name(),
        "scenes": {
            "selected": info.selected,
            "evaluated": done_records.len(),
            "null_in_index": info.null_entries,
            "missing_from_data": tally.missing,
            "skipped_fov": skipped_fov,
            "failed": tally.failed.iter().map(|(k, e)| json!({ "scene": k, "error": e })).collect::<Vec<_>>(),
            "excluded": req.exclude,
        },
        "images": images,
        "methods": table.iter().map(|(m, s)| (m.key().to_string(), json!(s))).collect::<serde_json::Map<_, _>>(),
        "per_scene": per_scene_json,
        "warnings": tally.warnings,
        "run": { "rendered": rendered.len(), "rescored": rescored.len(), "resumed": resumed.len(), "seconds": seconds },
    });
    write_json(&out.join(METRICS_JSON), &metrics)?;
    let line = format!(
        "Index `{}`, data `{}`, model {}: {} scene(s) evaluated ({} null in the index, {} missing from the data, {} skipped for field of view, {} failed), {} image(s) per method.",
        req.index.display(),
        info.data_dir.display(),
        cx.spec.description,
        done_records.len(),
        info.null_entries,
        tally.missing.len(),
        skipped_fov.len(),
        tally.failed.len(),
        images
    );
    output::write_bytes(&out.join(METRICS_MD), markdown(&line, &table, &per_scene_primary, primary, cx.spec.blend.is_some()).as_bytes())?;
    Ok(summary(out, info, tally, skipped_fov, images, table, Vec::new()))
}

fn summary(
    out: &Path,
    info: &RunInfo,
    tally: Tally,
    skipped_fov: Vec<String>,
    images: usize,
    methods: Vec<(Method, MethodScores)>,
    incomplete: Vec<String>,
) -> EvalSummary {
    EvalSummary {
        out: out.to_path_buf(),
        selected: info.selected,
        null_entries: info.null_entries,
        rendered: tally.rendered,
        rescored: tally.rescored,
        resumed: tally.resumed,
        missing: tally.missing,
        skipped_fov,
        images,
        methods,
        warnings: tally.warnings,
        seconds: info.t_all.elapsed().as_secs_f64(),
        incomplete,
        failed: tally.failed,
    }
}
