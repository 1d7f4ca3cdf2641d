//! How the process asks the system for memory: glibc's thresholds for mapped blocks and
//! transparent huge pages. [`configure`] is the first thing `mcdenoise` does, and the speed
//! benchmark does the same, so that it measures the process as it runs.

/// Both settings below; call it first in `main`, before any thread starts (it may start the
/// process again).
pub fn configure() {
    use_huge_pages();
    tune_allocator();
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

/// Transparent huge pages for the allocator's large blocks (glibc's `glibc.malloc.hugetlb=1`
/// tunable: mapped blocks and heap growth advised with `MADV_HUGEPAGE`). Where the kernel
/// gives huge pages only to regions that ask for them (`madvise`, the usual default), a
/// frame's planes, the network's tensors and ONNX Runtime's arena are otherwise faulted in
/// 4 KB at a time: about 185,000 page faults for a 720p frame. glibc reads its tunables only
/// when a process starts, so with `MCDENOISE_HUGE_PAGES=on` the process starts itself again,
/// once, with the tunable added to `GLIBC_TUNABLES`; it does not when the tunable is set
/// already (by this or by the operator), or when the kernel's mode is `always` (every
/// process has them) or `never`. Asked for, not by default: on a fresh machine `mcdenoise
/// run` at 720p (2 threads, ten alternated pairs) took 2.98 → 2.66 s with them, but where
/// the machine's memory is fragmented the kernel compacts it on each fault of an advised
/// region (`defrag` `madvise`, the usual default): on an AMD EPYC after two CI runs, eight
/// alternated runs each, median 1.94 s without and 3.68 s (1.62–7.07) with, kernel time
/// 0.6–0.8 against 1.3–2.2 s a run (docs/results/speed-work.md).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn use_huge_pages() {
    use std::os::unix::process::CommandExt;

    const TUNABLE: &str = "glibc.malloc.hugetlb";
    if !std::env::var_os("MCDENOISE_HUGE_PAGES").is_some_and(|v| v == "on") {
        return;
    }
    let tunables = std::env::var("GLIBC_TUNABLES").unwrap_or_default();
    if tunables.contains(TUNABLE) {
        return;
    }
    let mode = std::fs::read_to_string("/sys/kernel/mm/transparent_hugepage/enabled").unwrap_or_default();
    if !mode.contains("[madvise]") {
        return;
    }
    let value = if tunables.is_empty() { format!("{TUNABLE}=1") } else { format!("{tunables}:{TUNABLE}=1") };
    let mut args = std::env::args_os();
    let arg0 = args.next().unwrap_or_else(|| "mcdenoise".into());
    // exec returns only if the process could not start again: it goes on as it is.
    let _ = std::process::Command::new("/proc/self/exe").arg0(arg0).args(args).env("GLIBC_TUNABLES", value).exec();
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn use_huge_pages() {}
