//! Pieces of the UniMatch code base that the multi-view backbone reuses (`backbone/unimatch/*` upstream).

pub mod backbone;
pub mod position;
pub mod utils;
