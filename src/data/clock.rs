//! Wall-clock dates and timestamps (UTC) for file names and metadata, through the `time` crate:
//! the one place the project turns a `SystemTime` into a calendar date.

use std::time::{SystemTime, UNIX_EPOCH};
use time::OffsetDateTime;

/// The UTC date-time of `t` (times before 1970 included; out-of-range times clamp to the epoch).
fn utc(t: SystemTime) -> OffsetDateTime {
    let nanos: i128 = match t.duration_since(UNIX_EPOCH) {
        Ok(d) => d.as_nanos() as i128,
        Err(e) => -(e.duration().as_nanos() as i128),
    };
    OffsetDateTime::from_unix_timestamp_nanos(nanos).unwrap_or(OffsetDateTime::UNIX_EPOCH)
}

/// `YYYY-MM-DD` (UTC) of a system time.
pub fn utc_date(t: SystemTime) -> String {
    let d = utc(t);
    format!("{:04}-{:02}-{:02}", d.year(), u8::from(d.month()), d.day())
}

/// RFC 3339 UTC to the second (`2026-11-21T16:05:00Z`) of a system time.
pub fn utc_timestamp(t: SystemTime) -> String {
    let d = utc(t);
    format!(
        "{}T{:02}:{:02}:{:02}Z",
        utc_date(t),
        d.hour(),
        d.minute(),
        d.second()
    )
}

/// Now, as [`utc_timestamp`].
pub fn utc_now() -> String {
    utc_timestamp(SystemTime::now())
}

/// Today's date (UTC), as [`utc_date`].
pub fn today() -> String {
    utc_date(SystemTime::now())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn at(secs: u64) -> SystemTime {
        UNIX_EPOCH + Duration::from_secs(secs)
    }

    #[test]
    fn dates_and_timestamps() {
        assert_eq!(utc_date(UNIX_EPOCH), "1970-01-01");
        // 2000-02-29 12:00 UTC = 951825600 s (a leap day of a year divisible by 400)
        assert_eq!(utc_date(at(951_825_600)), "2000-02-29");
        // 2026-11-21 00:00 UTC = 1795219200 s; one second earlier is still the 20th
        assert_eq!(utc_date(at(1_795_219_200)), "2026-11-21");
        assert_eq!(utc_timestamp(at(1_795_219_199)), "2026-11-20T23:59:59Z");
        assert_eq!(
            utc_timestamp(at(1_795_219_200 + 16 * 3600 + 5 * 60)),
            "2026-11-21T16:05:00Z"
        );
        assert_eq!(utc_date(UNIX_EPOCH - Duration::from_secs(1)), "1969-12-31");
    }
}
