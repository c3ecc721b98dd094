//! `host-sim` command line; all logic is in the library (`host_sim::cli`).
use clap::Parser;

fn main() -> std::process::ExitCode {
    match host_sim::cli::run(host_sim::cli::Cli::parse()) {
        Ok(msg) => {
            println!("{msg}");
            std::process::ExitCode::SUCCESS
        }
        Err(msg) => {
            eprintln!("error: {msg}");
            std::process::ExitCode::FAILURE
        }
    }
}
