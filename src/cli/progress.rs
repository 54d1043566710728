//! Progress bars of long command-line work (reading frames, fitting, writing labels), drawn by
//! indicatif on stderr when stderr is a terminal and hidden otherwise, so that logs and pipes
//! get only the summary lines. The fit reports through its plain callback
//! ([`crate::fit::Progress`]); only this module knows of indicatif.

use std::io::IsTerminal;
use std::ops::ControlFlow;

use indicatif::{ProgressBar, ProgressStyle};

use crate::fit::Progress;

/// Whether bars are drawn: stderr (where they go) is a terminal.
fn interactive() -> bool {
    std::io::stderr().is_terminal()
}

/// A bar of `len` steps named `what` (e.g. "reading frames"); hidden when not interactive.
pub fn bar(len: usize, what: &'static str) -> ProgressBar {
    if !interactive() {
        return ProgressBar::hidden();
    }
    let style = ProgressStyle::with_template("{msg:>16} [{bar:30}] {pos}/{len} {elapsed}, eta {eta}")
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> ");
    ProgressBar::new(len as u64).with_style(style).with_message(what)
}

/// Shows a fit's progress callbacks as one bar over every iteration of every window.
pub struct FitBar {
    bar: ProgressBar,
}

impl Default for FitBar {
    fn default() -> Self {
        Self::new()
    }
}

impl FitBar {
    /// A bar whose length is set by the first report.
    pub fn new() -> Self {
        if !interactive() {
            return Self { bar: ProgressBar::hidden() };
        }
        let style =
            ProgressStyle::with_template("{prefix:>16} [{bar:30}] {pos}/{len} iterations {elapsed}, eta {eta}  {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> ");
        Self { bar: ProgressBar::new(0).with_style(style).with_prefix("fitting") }
    }

    /// Takes one report of the fit; never cancels it.
    pub fn update(&mut self, p: &Progress) -> ControlFlow<()> {
        // A windowed fit runs `iterations` per window: the bar spans all of them.
        let (windows, window) = p.window.map_or((1, 0), |w| (w.windows, w.window));
        self.bar.set_length((windows * p.iterations) as u64);
        self.bar.set_position((window * p.iterations + p.iteration) as u64);
        if windows > 1 {
            self.bar.set_prefix(format!("window {}/{windows}", window + 1));
        }
        let message = match p.rigid_tracks {
            Some(t) => format!("moving bodies: {}/{} clusters", t.clusters_done, t.clusters),
            None => format!("loss {:.5}", p.loss.total),
        };
        self.bar.set_message(message);
        ControlFlow::Continue(())
    }

    /// Removes the bar (the summary lines follow it).
    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}
