//! The `drivescript` command line; each subcommand lives in `cli/`.

mod cli;

// candle allocates a fresh buffer for every tensor op; mimalloc reuses freed pages where the
// system allocator returned large blocks to the kernel and zeroed new ones.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    // Rust ignores SIGPIPE, so printing into a closed pipe (`drivescript ... | head`) makes
    // println! panic. A command-line tool should end quietly there, as cat and grep do.
    #[cfg(unix)]
    // SAFETY: restores the default disposition of one signal before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    // candle sizes its matrix products' thread pool with num_cpus::get_physical(), which
    // re-reads /proc/cpuinfo on every product unless RAYON_NUM_THREADS is set: a sixth of
    // unguided sampling's time. A user's own setting is kept.
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        let n = std::thread::available_parallelism().map_or(1, |n| n.get());
        // Sound only while the process is single-threaded, as it is here.
        std::env::set_var("RAYON_NUM_THREADS", n.to_string());
    }
    cli::run()
}
