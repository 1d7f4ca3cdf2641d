//! The `mcdenoise` command: offline denoising and preprocessing.

use clap::{Parser, Subcommand};
use tracing_subscriber::EnvFilter;

use mcdenoise::cli;

/// Denoiser for Monte Carlo path-traced frames (kernel-predicting CNNs on ONNX Runtime).
#[derive(Parser, Debug)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Denoise one EXR frame and print per-stage timings (and metrics with --reference).
    Run(cli::RunArgs),
    /// Write the network inputs of one frame (and training targets) as .npz.
    Preprocess(cli::PreprocessArgs),
    /// Print RelMSE, DSSIM, PSNR and SMAPE of an image against a reference as JSON.
    Metrics(cli::MetricsArgs),
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("warn")))
        .with_writer(std::io::stderr)
        .init();
    let result = match Cli::parse().command {
        Command::Run(args) => cli::run(args),
        Command::Preprocess(args) => cli::preprocess(args),
        Command::Metrics(args) => cli::metrics(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
