//! The `mcdenoise` command: offline denoising and preprocessing, the daemon, its client.

use clap::{Parser, Subcommand};
use tracing_subscriber::EnvFilter;

use mcdenoise::{cli, client, config, memory, server};

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
    /// Run the denoising daemon: HTTP and gRPC job API, persistent queue (docs/api.md).
    Serve(Box<config::ServeArgs>),
    /// Submit a frame to a daemon, optionally wait for it and fetch the result.
    Submit(client::SubmitArgs),
}

fn init_cli_logging() {
    tracing_subscriber::fmt()
        .with_env_filter(EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("warn")))
        .with_writer(std::io::stderr)
        .init();
}

fn main() -> std::process::ExitCode {
    memory::configure();
    let result = match Cli::parse().command {
        Command::Run(args) => {
            init_cli_logging();
            cli::run(args)
        }
        Command::Preprocess(args) => {
            init_cli_logging();
            cli::preprocess(args)
        }
        Command::Metrics(args) => {
            init_cli_logging();
            cli::metrics(args)
        }
        Command::Serve(args) => {
            // With a config file, parse again so that the file supplies the defaults.
            let args = if args.config.is_some() {
                let argv = std::env::args_os().skip_while(|a| a != "serve");
                config::parse_serve_args(argv)
            } else {
                args.validate().map(|()| *args)
            };
            args.and_then(server::serve)
        }
        Command::Submit(args) => {
            init_cli_logging();
            client::submit(args)
        }
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // clap's own errors are already worded for the terminal (and exit with 2).
            if let Some(usage) = e.downcast_ref::<clap::Error>() {
                let _ = usage.print();
                return std::process::ExitCode::from(2);
            }
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
