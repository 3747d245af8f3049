//! Runs a capsule-slam pipeline over a dataset ([`runner::run`]) and writes its output folder as
//! it goes ([`writer::RunWriter`]): `config.toml` first, then per frame `trajectory.txt`,
//! `frames.csv` and `counters.jsonl` (flushed), at the end `map.ply` and `summary.json`, with
//! the evaluation against the input's ground truth when it has one.

pub mod runner;
pub mod summary;
pub mod truth;
pub mod writer;

pub use runner::{GT_SURFACE_FILE, RunOptions, run, run_observed, written_map};
pub use summary::{BuildStamp, Summary};
pub use writer::RunWriter;
