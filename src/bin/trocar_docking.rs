//! The offline CLI: `trocar_docking --help`.

use clap::Parser;

fn main() {
    let cli = trocar_docking::cli::Cli::parse();
    if let Err(e) = trocar_docking::cli::run(cli) {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}
