pub mod bench;
pub mod convert;
pub mod export;
pub mod inspect;
