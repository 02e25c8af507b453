//! Simulated instrument (lands with the physics core).
