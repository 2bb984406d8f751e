//! The `drivescript` command line; each subcommand lives in `cli/`.

mod cli;

// candle allocates a fresh buffer for every tensor op; the system allocator hands large ones
// back to the kernel each time, and the page faults that follow took about as much CPU time as
// the arithmetic (sampling and training, `bench sample`).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    cli::run()
}
