//! Reading a recording back: which entities it holds and how many rows each has (what a test
//! checks, and what a user can print to see what a file holds).

use std::collections::BTreeMap;
use std::path::Path;

use rerun::external::re_log_encoding::DecoderApp;
use rerun::log::{Chunk, LogMsg};

use crate::error::RecordError;

/// A recording's entities (paths as rerun prints them, e.g. `/world/camera`) and their rows.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Contents {
    /// Rows logged per entity, over all times (static rows included).
    pub rows: BTreeMap<String, u64>,
}

impl Contents {
    /// The rows of `entity` (with or without the leading `/`), 0 if absent.
    pub fn rows_of(&self, entity: &str) -> u64 {
        let key = if entity.starts_with('/') { entity.to_owned() } else { format!("/{entity}") };
        self.rows.get(&key).copied().unwrap_or(0)
    }
}

/// Decodes the recording at `path`.
pub fn contents(path: &Path) -> Result<Contents, RecordError> {
    let read_error = |message: String| RecordError::Read { path: path.to_owned(), message };
    let file = std::fs::File::open(path).map_err(|e| read_error(e.to_string()))?;
    let decoder = DecoderApp::decode_eager(std::io::BufReader::new(file)).map_err(|e| read_error(e.to_string()))?;
    let mut out = Contents::default();
    for msg in decoder {
        if let LogMsg::ArrowMsg(_, arrow) = msg.map_err(|e| read_error(e.to_string()))? {
            let chunk = Chunk::from_arrow_msg(&arrow).map_err(|e| read_error(e.to_string()))?;
            *out.rows.entry(chunk.entity_path().to_string()).or_default() += chunk.num_rows() as u64;
        }
    }
    Ok(out)
}
