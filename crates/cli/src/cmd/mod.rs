pub mod bench;
pub mod convert;
pub mod export;
pub mod inspect;
pub mod progress;
pub mod render;
pub mod views;
pub mod weights;
