//! (module under construction: see docs/)
