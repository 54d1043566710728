//! Subcommands of the `mbnt` binary; `src/main.rs` only parses arguments and calls these.

pub mod serve_cmd;
