//! Programs that measure or diagnose the model and are not part of the product: the examples of this crate
//! (`cargo run --release -p mvsplat360-lab --example NAME`). Concluded explorations are deleted; their studies in
//! `docs/research/` name the commit where their code last lived.
