//! Register data only (see Cargo.toml); never built.
