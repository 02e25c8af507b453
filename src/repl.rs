//! Interactive REPL (rustyline).
