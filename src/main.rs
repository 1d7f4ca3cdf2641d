//! The `mcdenoise` command: offline denoising and preprocessing, the daemon, its client.

use clap::{Parser, Subcommand};
use tracing_subscriber::EnvFilter;

use mcdenoise::{cli, client, config, server};

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

/// Allocations of 4 MB and more (a 4K frame's planes, a region's tensors, ONNX Runtime's
/// arena extensions) are mapped and unmapped one by one, so that what a large frame frees
/// goes back to the system; smaller blocks (a 720p frame's planes are 1.8–3.7 MB) come from
/// the heaps, which keep up to 128 MB free at their top, so that the next stage reuses the
/// pages the last one freed instead of having the kernel fault in and zero new ones.
/// glibc's default mmap threshold starts at 128 KB and rises to the largest block freed (up
/// to 32 MB), after which a 4K frame's planes come from heaps that several threads fragment:
/// `mcdenoise run` on one 3840×2160 frame peaked anywhere between 1.37 and 1.53 GB from run
/// to run. With a fixed 1 MB threshold it peaked at 1.43–1.46 GB, and with these two values
/// at 1.47 GB in 30 s instead of 31–34 s, while a 720p run spends a third less time in the
/// kernel (docs/results/speed-work.md).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn tune_allocator() {
    // SAFETY: mallopt only sets parameters of the allocator; called before any thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 4 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 128 << 20);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn tune_allocator() {}

fn main() -> std::process::ExitCode {
    tune_allocator();
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
