//! `capsule-slam config --default`.

use anyhow::bail;
use capsule_slam_framework::config::default_text::default_config_text;

/// Arguments of `config`.
#[derive(clap::Args, Debug)]
pub struct ConfigArgs {
    /// Print the complete, commented default configuration.
    #[arg(long)]
    default: bool,
}

pub fn run(args: &ConfigArgs) -> anyhow::Result<()> {
    if !args.default {
        bail!("nothing to do: use `capsule-slam config --default` to print the default configuration");
    }
    print!("{}", default_config_text(&crate::registry()?));
    Ok(())
}
