//! The data-parallel reduction of one step: loss sums and gradients summed over the ranks.

use super::*;

/// One rank's sums of a step, before the all-reduce (losses already divided by the step's micro-batch count).
pub(super) struct StepSums<'a> {
    pub(super) loss: f64,
    pub(super) mse: f64,
    pub(super) lpips: Option<f64>,
    pub(super) n_lpips: usize,
    pub(super) refiner: Option<(f64, f64)>,
    pub(super) n_refiner: usize,
    pub(super) vae: Option<(f64, f64)>,
    /// This rank's depth terms (their mean over all ranks is logged).
    pub(super) depth: &'a [f64],
    pub(super) stop: bool,
}

pub(super) struct Reduced {
    pub(super) loss: f64,
    pub(super) mse: f64,
    pub(super) lpips: Option<f64>,
    pub(super) refiner: Option<(f64, f64)>,
    pub(super) vae: Option<(f64, f64)>,
    pub(super) depth: Option<f64>,
    pub(super) stop: bool,
}

/// Sums the step's losses and gradients over the ranks. A parameter without a gradient on some rank adds
/// zeros there; it keeps none only when no rank has one (as in one process).
pub(super) fn reduce_step(c: &mut dyn crate::dist::Collective, s: StepSums, grads: &mut [Option<Tensor>], params: &[Param], dev: &Device) -> Result<Reduced> {
    let (lp, rf) = (s.lpips.unwrap_or(0.0), s.refiner.unwrap_or((0.0, 0.0)));
    let mut v = vec![
        s.loss,
        s.mse,
        lp,
        s.n_lpips as f64,
        rf.0,
        rf.1,
        s.n_refiner as f64,
        s.depth.iter().sum::<f64>(),
        s.depth.len() as f64,
        s.stop as u8 as f64,
        s.vae.unwrap_or((0.0, 0.0)).0,
        s.vae.unwrap_or((0.0, 0.0)).1,
        s.vae.is_some() as u8 as f64,
    ];
    const HEAD: usize = 13;
    v.extend(grads.iter().map(|g| g.is_some() as u8 as f64));
    c.all_reduce_f64(&mut v)?;
    let present: Vec<usize> = (0..grads.len()).filter(|&i| v[HEAD + i] > 0.0).collect();
    if !present.is_empty() {
        let parts = present
            .iter()
            .map(|&i| match &grads[i] {
                Some(g) => g.flatten_all(),
                None => Tensor::zeros(params[i].var.elem_count(), DType::F32, dev),
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        let sum = c.all_reduce_tensor(&Tensor::cat(&parts, 0)?)?;
        let mut off = 0;
        for &i in &present {
            let n = params[i].var.elem_count();
            grads[i] = Some(sum.narrow(0, off, n)?.reshape(params[i].var.dims())?);
            off += n;
        }
    }
    Ok(Reduced {
        loss: v[0],
        mse: v[1],
        lpips: (v[3] > 0.0).then_some(v[2]),
        refiner: (v[6] > 0.0).then_some((v[4], v[5])),
        depth: (v[8] > 0.0).then(|| v[7] / v[8]),
        stop: v[9] > 0.0,
        vae: (v[12] > 0.0).then_some((v[10], v[11])),
    })
}
