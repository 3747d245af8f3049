//! The tracker's modes as its config names them: what the live frame is registered to, what
//! its photometric term compares with, and its motion prior.

use serde::{Deserialize, Serialize};

/// What the live frame is registered to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Mode {
    /// The prediction of the fused active model (the paper), filled in by the last frame.
    FrameToModel,
    /// The previous live frame only (for comparison).
    FrameToFrame,
}

/// What the photometric term compares the live image with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RgbReference {
    /// The previous live frame (lit like the current one).
    PreviousFrame,
    /// The last keyframe, replaced as the views drift apart (`keyframe.rs`): frame-to-frame
    /// errors stop adding up between keyframes.
    Keyframe,
    /// The predicted model colour (the paper).
    Model,
    /// The last keyframe and the previous frame at once, one photometric row against each per
    /// live pixel: the keyframe stops the previous frame's walk, the previous frame holds where
    /// the keyframe's longer baseline carries the depth's error into the warp (weigh that by
    /// `rgb_flow_sigma_scale`). For depth whose error is correlated across the image
    /// (`docs/results/depth-noise.md`, "The keyframe and the previous frame at once").
    KeyframeAndPrevious,
    /// `keyframe-and-previous` where the frame's depth error is correlated across pixels (its
    /// σ declares a `correlation_px` > 0: `camera.toml`'s `depth_noise`, `stereo-sgm`'s depth)
    /// and a light model relights the photometric term, else `previous-frame`. Such an error
    /// cannot anchor the pose through ICP (counted once per correlated patch), so the
    /// photometric term carries it, and against the previous frame alone it walks. Without
    /// the relighting a capsule's moving light changes the wall's brightness across a
    /// keyframe's baseline (about 20 % for 3 mm at 30 mm): on a fast stereo phantom without
    /// `light.toml` the keyframe's rows took the ATE from 0.61 to 1.64 % of the path
    /// (`docs/results/depth-noise.md`). A room lit by lamps that stay put needs no relighting:
    /// set `keyframe-and-previous` there.
    Auto,
}

impl RgbReference {
    /// Whether this reference keeps a keyframe (`keyframe.rs`).
    pub fn keeps_keyframe(self) -> bool {
        matches!(self, Self::Keyframe | Self::KeyframeAndPrevious)
    }

    /// The reference for a frame whose depth error is correlated over `correlation_px` pixels
    /// (0: independent from pixel to pixel), `relit` where a light model relights the
    /// photometric term: [`RgbReference::Auto`] resolved, the others as they are.
    pub fn for_frame(self, correlation_px: f64, relit: bool) -> Self {
        match self {
            Self::Auto if correlation_px > 0.0 && relit => Self::KeyframeAndPrevious,
            Self::Auto => Self::PreviousFrame,
            other => other,
        }
    }
}

/// The motion prior.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MotionModel {
    /// Start from the last pose.
    None,
    /// Start from the last pose moved by the last relative motion.
    ConstantVelocity,
}
