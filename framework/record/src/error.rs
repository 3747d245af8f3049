//! The recording's errors.

use std::path::PathBuf;

/// What went wrong with a recording; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// The file could not be created (a missing folder, no permission).
    #[error("{path}: cannot create the recording: {message}; check that its folder exists and is writable")]
    Create {
        /// The recording.
        path: PathBuf,
        /// rerun's reason.
        message: String,
    },
    /// An entity could not be logged.
    #[error("{path}: logging {entity}: {message}")]
    Log {
        /// The recording.
        path: PathBuf,
        /// The entity path.
        entity: String,
        /// rerun's reason.
        message: String,
    },
    /// The file could not be completed.
    #[error("{path}: finishing the recording: {message}")]
    Flush {
        /// The recording.
        path: PathBuf,
        /// rerun's reason.
        message: String,
    },
    /// A recording could not be read back.
    #[error("{path}: not a readable rerun recording: {message}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The decoder's reason.
        message: String,
    },
}
