//! What a QPD digitiser's inputs can measure: the input range (a sample at or beyond its rail is
//! *clipped*, its value meaningless beyond "at least this much") and the floor of the sum
//! signal below which the detector is *dark* (laser off, beam blocked).
//!
//! Every backend knows its range: the NI board's `range_v`, the Red Pitaya's LV/HV jumpers
//! (±1 V / ±20 V), the SCPI digitiser's `range_v` from the config, the KPA101's ADC (±10 V
//! differences, 0–10 V sum over its 16-bit counts), the simulator's `detector_range` effect.
//! Drivers count the clipped samples of each read (`QpdReading::clipped`) and flag them per
//! sample in buffered traces and streams; the scan engine counts them per pixel
//! (`acquire::clip`) and the analyses warn about them (`data::clip`).

pub use crate::data::clip::{at_rail, InputRange, RAIL_MARGIN};

/// Per-sample clip flags of a buffered trace or a stream chunk: bit 0 Sx, bit 1 Sy, bit 2 Sz.
pub const CLIP_SX: u8 = 1;
pub const CLIP_SY: u8 = 2;
pub const CLIP_SZ: u8 = 4;

/// The flag byte of one sample whose three signals' inputs are `[sx, sy, sz]` at the rail.
pub fn clip_bits(clipped: [bool; 3]) -> u8 {
    (clipped[0] as u8) | ((clipped[1] as u8) << 1) | ((clipped[2] as u8) << 2)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_flag_byte_has_a_bit_per_signal() {
        assert_eq!(clip_bits([true, false, true]), CLIP_SX | CLIP_SZ);
        assert_eq!(clip_bits([false, true, false]), CLIP_SY);
    }
}
