//! The official `vggt/heads/`: the camera head and the DPT heads (depth, points), their activations and the
//! DPT positional embedding. `track_head` is not ported (the project does not track points).

pub mod camera_head;
pub mod dpt_head;
pub mod head_act;
pub mod utils;
