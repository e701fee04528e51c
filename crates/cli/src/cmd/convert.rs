//! `mvsplat360 convert`: any supported checkpoint (safetensors, Lightning `.ckpt`, `.pth`) → safetensors.

use std::path::PathBuf;

use anyhow::Context;

#[derive(clap::Args)]
pub struct Args {
    /// Input checkpoint: a safetensors file or a torch zip checkpoint (Lightning `.ckpt`, `.pth`); torch files
    /// are read from their `state_dict` entry when they have one.
    input: PathBuf,
    /// Output safetensors file.
    #[arg(long)]
    out: PathBuf,
    /// Keep only tensors whose name starts with this prefix (names are kept verbatim, so the encoder's keys keep
    /// their `encoder.` prefix). Pass an empty string to keep every tensor.
    #[arg(long, default_value = "encoder.")]
    prefix: String,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.out == args.input {
        anyhow::bail!("--out must differ from the input file {}", args.input.display());
    }
    let n = mvsplat360_encoder::weights::convert_to_safetensors(&args.input, &args.out, &args.prefix)
        .with_context(|| format!("converting {} to {}", args.input.display(), args.out.display()))?;
    eprintln!("wrote {n} tensors with prefix `{}` to {}", args.prefix, args.out.display());
    Ok(())
}
