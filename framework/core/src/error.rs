//! Typed errors of the framework. Outcomes such as tracking loss or "no loop found" are values
//! ([`crate::stage::TrackStatus`], `Option<LoopClosure>`), never errors.

use std::path::PathBuf;

/// An error raised by a stage while processing a frame.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StageError {
    /// The frame does not carry what the stage needs (e.g. no depth for the `sensor` estimator).
    #[error("invalid input: {message}")]
    InvalidInput {
        /// What is missing or wrong, and how to fix it.
        message: String,
    },
    /// A numerical failure (singular system, NaN) that the stage could not turn into a value.
    #[error("numerical failure: {message}")]
    Numerical {
        /// What failed.
        message: String,
    },
    /// A GPU device error.
    #[error("GPU error: {message}")]
    Gpu {
        /// The device's message.
        message: String,
    },
    /// A plugin's own error, with the plugin's registry name.
    #[error("plugin `{name}`: {source}")]
    Plugin {
        /// Registry name of the plugin.
        name: String,
        /// The plugin's error.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

impl StageError {
    /// Shorthand for [`StageError::InvalidInput`].
    pub fn invalid_input(message: impl Into<String>) -> Self {
        Self::InvalidInput { message: message.into() }
    }
}

/// One problem found while validating a configuration: where, what, and how to fix it.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConfigProblem {
    /// Dotted key path, e.g. `plugins.surfel-cpu.delta_t` or `pipeline.depth`.
    pub key: String,
    /// What is wrong.
    pub message: String,
    /// What to do about it.
    pub fix: String,
}

impl ConfigProblem {
    /// Builds a problem.
    pub fn new(key: impl Into<String>, message: impl Into<String>, fix: impl Into<String>) -> Self {
        Self { key: key.into(), message: message.into(), fix: fix.into() }
    }
}

impl std::fmt::Display for ConfigProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {} (fix: {})", self.key, self.message, self.fix)
    }
}

/// Every problem of a configuration, reported at once.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{} in {source_name}:\n{}", plural(self.problems.len()), list(&self.problems))]
pub struct ConfigError {
    /// Where the configuration came from (a file path or "built-in default").
    pub source_name: String,
    /// All problems found.
    pub problems: Vec<ConfigProblem>,
}

fn plural(n: usize) -> String {
    if n == 1 { "1 configuration problem".into() } else { format!("{n} configuration problems") }
}

fn list(problems: &[ConfigProblem]) -> String {
    problems.iter().map(|p| format!("  - {p}")).collect::<Vec<_>>().join("\n")
}

/// An error reading input data or writing output. Always names the file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LoadError {
    /// The file could not be opened, read or written.
    #[error("{}: {error}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error (in the message, not a separate source: a chain printed by anyhow would
        /// repeat it).
        error: std::io::Error,
    },
    /// A text file has a malformed line (or, at line 0, is at fault as a whole).
    #[error("{}: {message}", at_line(path, *line))]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number (0 when the whole file is at fault).
        line: usize,
        /// What was expected and what was found.
        message: String,
    },
    /// An image could not be decoded or has the wrong size or type.
    #[error("{}: {message}", path.display())]
    Image {
        /// The image file.
        path: PathBuf,
        /// What is wrong, with the expected format.
        message: String,
    },
}

impl LoadError {
    /// Wraps an I/O error with its path.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io { path: path.into(), error: source }
    }
    /// A parse error at a line.
    pub fn parse(path: impl Into<PathBuf>, line: usize, message: impl Into<String>) -> Self {
        Self::Parse { path: path.into(), line, message: message.into() }
    }
}

/// `path:line`, or the path alone for line 0 (the whole file).
fn at_line(path: &std::path::Path, line: usize) -> String {
    if line == 0 { path.display().to_string() } else { format!("{}:{line}", path.display()) }
}

/// An error in the plugin registry.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum RegistryError {
    /// Two plugins registered the same name.
    #[error("duplicate plugin name `{name}` (a {first} and a {second}); plugin names must be unique")]
    Duplicate {
        /// The clashing name.
        name: String,
        /// Stage kind of the first registration.
        first: String,
        /// Stage kind of the second registration.
        second: String,
    },
    /// A shared-library plugin could not be loaded.
    #[error("plugin library {}: {message} (fix: {fix})", path.display())]
    Library {
        /// The library's path.
        path: std::path::PathBuf,
        /// What is wrong.
        message: String,
        /// What to do about it.
        fix: String,
    },
}

/// An error that stops a run.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PipelineError {
    /// A stage failed on a frame.
    #[error("frame {frame}: stage `{stage}` failed: {source}")]
    Stage {
        /// Frame index.
        frame: usize,
        /// Registry name of the plugin.
        stage: String,
        /// The stage's error.
        source: StageError,
    },
    /// The configuration is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// Reading input or writing output failed.
    #[error(transparent)]
    Load(#[from] LoadError),
    /// Reading a frame's input failed.
    #[error("at frame {frame}: {source}")]
    LoadAt {
        /// Frame index.
        frame: usize,
        /// What could not be read.
        source: LoadError,
    },
    /// Every frame ran, but the run could not do its job (e.g. no frame gave usable depth, so
    /// there is no map): what it wrote is kept, its summary says so.
    #[error("{0}")]
    NoResult(String),
    /// Frames handed to the pipeline out of order (a `process` while a pushed frame waits).
    #[error("{0}")]
    Order(String),
}
