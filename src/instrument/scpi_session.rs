//! One SCPI session over a [`LineLink`], shared by the SCPI QPD digitiser and the Red Pitaya
//! board: a command is followed by the error queue (`SYST:ERR?`, IEEE 488.2 / SCPI-99 §21.8:
//! `<code>,"<message>"`, 0 = no error); a query that gets no reply within the timeout asks the
//! queue once, because a rejected query is never answered and the queue says why. Every error
//! names the device and the command.

use super::link::LineLink;
use super::DeviceError;
use std::time::Duration;

/// Parse a `SYST:ERR?` reply: `<code>,"<message>"`.
pub fn parse_scpi_error(reply: &str) -> Option<(i64, String)> {
    let (code, msg) = reply.split_once(',')?;
    let code = code.trim().parse::<i64>().ok()?;
    let msg = msg.trim();
    let msg = msg.strip_prefix('"')?.strip_suffix('"')?;
    Some((code, msg.to_string()))
}

/// The SCPI exchanges of a line link (`timeout`: the longest wait for a reply).
pub trait ScpiSession {
    /// `SYST:ERR?`; a nonzero code is a `Controller` error naming `after`.
    fn check_error(&mut self, after: &str, timeout: Duration) -> Result<(), DeviceError>;
    /// Send a command without reply, then check the error queue.
    fn scpi_command(&mut self, command: &str, timeout: Duration) -> Result<(), DeviceError>;
    /// Send a query and return its reply line; on a timeout the error queue is asked once, and
    /// an error there is the answer (it explains the silence).
    fn scpi_query(&mut self, command: &str, timeout: Duration) -> Result<String, DeviceError>;
}

impl ScpiSession for LineLink {
    fn check_error(&mut self, after: &str, timeout: Duration) -> Result<(), DeviceError> {
        let label = format!("SYST:ERR? (after `{after}`)");
        let line = self
            .query_with_timeout("SYST:ERR?", timeout)
            .map_err(|e| e.during(&label))?;
        match parse_scpi_error(&line) {
            Some((0, _)) => Ok(()),
            Some((code, message)) => Err(DeviceError::Controller {
                device: self.device().to_string(),
                command: after.to_string(),
                code,
                message,
            }),
            None => Err(self.garbled(&label, line)),
        }
    }

    fn scpi_command(&mut self, command: &str, timeout: Duration) -> Result<(), DeviceError> {
        self.discard_input();
        self.send(command)?;
        self.check_error(command, timeout)
    }

    fn scpi_query(&mut self, command: &str, timeout: Duration) -> Result<String, DeviceError> {
        match self.query_with_timeout(command, timeout) {
            Ok(l) => Ok(l),
            Err(e @ DeviceError::Timeout { .. }) => match self.check_error(command, timeout) {
                Err(c @ DeviceError::Controller { .. }) => Err(c),
                _ => Err(e),
            },
            Err(e) => Err(e),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::instrument::link::mock::link;

    #[test]
    fn a_command_reads_the_error_queue_and_names_what_it_rejected() {
        let t = Duration::from_millis(20);
        let mut l = link(vec![b"", b"0,\"No error\"\n"]);
        assert!(l.scpi_command("*CLS", t).is_ok());
        let mut l = link(vec![b"", b"-222,\"Data out of range\"\n"]);
        let e = l
            .scpi_command("SENS:AVER:COUN 0", t)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("SENS:AVER:COUN 0") && e.contains("-222") && e.contains("Data out of range"),
            "{e}"
        );
    }

    #[test]
    fn a_silent_query_is_explained_by_the_queue_else_a_timeout() {
        let t = Duration::from_millis(20);
        let mut l = link(vec![b"", b"-113,\"Undefined header\"\n"]);
        let e = l.scpi_query("FOO?", t).unwrap_err().to_string();
        assert!(e.contains("FOO?") && e.contains("Undefined header"), "{e}");
        let mut l = link(vec![b"", b"0,\"No error\"\n"]);
        assert!(matches!(
            l.scpi_query("FOO?", t),
            Err(DeviceError::Timeout { .. })
        ));
        let mut l = link(vec![b"1.5\n"]);
        assert_eq!(l.scpi_query("CONF:RATE?", t).unwrap(), "1.5");
    }

    #[test]
    fn error_replies_parse() {
        assert_eq!(
            parse_scpi_error("-222,\"Data out of range\""),
            Some((-222, "Data out of range".into()))
        );
        assert_eq!(
            parse_scpi_error("0, \"No error\" "),
            Some((0, "No error".into()))
        );
        assert_eq!(parse_scpi_error("No error"), None);
    }
}
