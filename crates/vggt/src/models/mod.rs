//! The official `vggt/models/`: the aggregator (alternating frame and global attention) and the full model.

pub mod aggregator;
pub mod vggt;
