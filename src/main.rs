//! The `drivescript` command line; each subcommand lives in `cli/`.

mod cli;

use std::io::Write;

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
    // println! panics when stdout cannot take the text (a full disk, /dev/full): a failed
    // write of the output is an error of the run, said in one line, not a crash.
    let default_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let payload = info.payload();
        let message = payload
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| payload.downcast_ref::<&str>().copied());
        match message {
            Some(m) if m.starts_with("failed printing to stdout") => {
                let why = m.trim_start_matches("failed printing to stdout: ");
                // Not eprintln!: a second failure inside the hook would abort.
                let _ = writeln!(
                    std::io::stderr(),
                    "error: cannot write the output to standard output: {why}"
                );
                std::process::exit(1);
            }
            // Nowhere left to say it.
            Some(m) if m.starts_with("failed printing to stderr") => std::process::exit(1),
            _ => default_hook(info),
        }
    }));
    // candle sizes its matrix products' thread pool with num_cpus::get_physical(), which
    // re-reads /proc/cpuinfo on every product unless RAYON_NUM_THREADS is set: a sixth of
    // unguided sampling's time. A user's own setting is kept.
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        let n = std::thread::available_parallelism().map_or(1, |n| n.get());
        // Sound only while the process is single-threaded, as it is here.
        std::env::set_var("RAYON_NUM_THREADS", n.to_string());
    }
    // Cost scripts run on this thread (`cost`, `simulate`, `ask`, ...): it gets the stack
    // that the deepest data a script may build needs (`SCRIPT_STACK_BYTES`); a main thread's
    // 8 MB overflowed comparing or printing arrays nested 5,000 deep, and aborted.
    let big = std::thread::Builder::new()
        .name("main".into())
        .stack_size(drivescript::cost::SCRIPT_STACK_BYTES)
        .spawn(cli::run);
    match big {
        Ok(handle) => handle
            .join()
            .unwrap_or_else(|payload| std::panic::resume_unwind(payload)),
        // Where no such thread can be had (a tight `ulimit -v`), on this one.
        Err(_) => cli::run(),
    }
}
