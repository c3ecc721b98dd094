//! piezo-link: the one wire protocol between a host and the piezo firmware.
//!
//! A **packet** is `{sequence, body}` ([`Packet`]): the host sends [`Request`]s, the firmware sends
//! [`Uplink`]s (a [`Response`] naming the request's sequence number, or a sample [`Frame`]). Each
//! side numbers its own packets +1 per packet sent, so the receiver counts lost packets with a
//! [`SequenceChecker`]; frames carry their own frame number as well (the loop's count of
//! produced frames), so frames dropped before the link are seen too.
//!
//! On the wire (both directions):
//!
//! ```text
//! raw     = postcard(packet) ‖ CRC-32/ISO-HDLC(postcard(packet)) as 4 bytes LE
//! frame   = COBS(raw) ‖ 0x00                       firmware → host ([`encode`])
//! request = 0x00 ‖ COBS(raw) ‖ 0x00                host → firmware ([`encode_request`])
//! ```
//!
//! postcard is serde's compact binary format (varint integers, f32 as 4 bytes LE); COBS removes
//! every 0x00 from the packet so the 0x00 delimiter resynchronises a receiver after any byte lost
//! or corrupted. A request starts with a delimiter too, so that bytes a previous host left in the
//! firmware's decoder (half a frame) end there as one refused frame instead of swallowing the
//! request; the empty frame between two delimiters is ignored. A frame whose COBS or CRC check
//! fails, whose body does not parse, or that has bytes after its body, is refused
//! ([`DecodeError`]) and counted; a request lost that way is not answered (the host times out
//! and sees the gap in the firmware's request count).
//!
//! **Versions**: [`PROTOCOL_VERSION`] is the first field of every [`Status`]; a host reads it
//! before the rest ([`protocol_of_status`]) and refuses to talk to a firmware that speaks
//! another version, naming both.
//!
//! **Replays**: the firmware runs a request only if its sequence number is ahead of the last one
//! it handled ([`SequenceChecker::admit`]); any other is answered with [`Response::Replayed`]
//! naming the next number it runs, counted (`replayed_requests`), and not run. A host that starts
//! (and counts from 0) learns the number from that answer and sends its request again.
//!
//! Everything is fixed capacity (`heapless`) and caller-supplied: [`encode`] writes into a
//! `&mut [u8]`, [`Decoder`] accumulates up to [`MAX_FRAME`] bytes. Nothing allocates or panics.
//!
//! [`text`] owns the other form a sample frame takes: the one-line text the firmware images print
//! and `host-sim capture` reads.

#![cfg_attr(not(test), no_std)]

mod cobs;
mod message;
mod sequence;
mod state;
pub mod text;

pub use message::*;
/// The loop's own types, carried as they are: an axis's output limits and the reference
/// programs of [`Request::Track`] and [`Request::Excite`] (piezo-core, serde derives).
pub use piezo_core::{Limits, Program, Wave};
pub use sequence::SequenceChecker;
pub use state::*;

use serde::{de::DeserializeOwned, Deserialize, Serialize};

/// Largest encoded frame, delimiter included \[bytes\]: every message fits (checked by tests).
pub const MAX_FRAME: usize = 640;
/// Largest raw packet (postcard + CRC) that [`encode`] accepts \[bytes\].
pub const MAX_RAW: usize = MAX_FRAME - MAX_FRAME / 254 - 2;

const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// A numbered message.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Packet<T> {
    /// The sender's packet number (+1 per packet, wraps).
    pub sequence: u32,
    /// The message.
    pub body: T,
}

/// Why a packet could not be encoded or decoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DecodeError {
    /// The packet does not fit [`MAX_FRAME`] (encode), or a frame was longer (decode).
    TooLong,
    /// The COBS stuffing is broken (a byte lost or changed).
    Cobs,
    /// Fewer bytes than a CRC.
    TooShort,
    /// The CRC does not match.
    Crc,
    /// The CRC holds but the body is not a message of the expected type.
    Body,
    /// The CRC holds and a message parses, but bytes follow it.
    Trailing,
}

impl core::fmt::Display for DecodeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            DecodeError::TooLong => "frame longer than the link's maximum",
            DecodeError::Cobs => "broken COBS stuffing",
            DecodeError::TooShort => "frame shorter than its CRC",
            DecodeError::Crc => "CRC mismatch",
            DecodeError::Body => "CRC holds but the body does not parse",
            DecodeError::Trailing => "CRC holds but bytes follow the body",
        })
    }
}

/// Encodes `packet` into `out` as one delimited frame; returns its length.
pub fn encode<T: Serialize>(packet: &Packet<T>, out: &mut [u8]) -> Result<usize, DecodeError> {
    let mut raw = [0u8; MAX_RAW];
    let body_len = postcard::to_slice(packet, &mut raw[..MAX_RAW - 4])
        .map_err(|_| DecodeError::TooLong)?
        .len();
    let crc = CRC.checksum(&raw[..body_len]).to_le_bytes();
    let raw_len = body_len + 4;
    raw.get_mut(body_len..raw_len)
        .ok_or(DecodeError::TooLong)?
        .copy_from_slice(&crc);
    let n = cobs::encode(&raw[..raw_len], out).ok_or(DecodeError::TooLong)?;
    *out.get_mut(n).ok_or(DecodeError::TooLong)? = 0;
    Ok(n + 1)
}

/// Encodes a request: a 0x00 (ending whatever the receiver's decoder holds), then the frame of
/// [`encode`]; returns its length (at most [`MAX_FRAME`] + 1).
pub fn encode_request<T: Serialize>(
    packet: &Packet<T>,
    out: &mut [u8],
) -> Result<usize, DecodeError> {
    let (first, rest) = out.split_first_mut().ok_or(DecodeError::TooLong)?;
    *first = 0;
    Ok(encode(packet, rest)? + 1)
}

/// Decodes one frame (without its 0x00 delimiter), in place.
pub fn decode<T: DeserializeOwned>(frame: &mut [u8]) -> Result<Packet<T>, DecodeError> {
    let n = cobs::decode_in_place(frame).ok_or(DecodeError::Cobs)?;
    if n < 4 {
        return Err(DecodeError::TooShort);
    }
    let (body, crc) = frame[..n].split_at(n - 4);
    let mut expected = [0u8; 4];
    expected.copy_from_slice(crc);
    if CRC.checksum(body) != u32::from_le_bytes(expected) {
        return Err(DecodeError::Crc);
    }
    match postcard::take_from_bytes(body) {
        Ok((packet, [])) => Ok(packet),
        Ok(_) => Err(DecodeError::Trailing),
        Err(_) => Err(DecodeError::Body),
    }
}

/// The [`Status::protocol`] of a frame (without its delimiter) that holds a status answer, read
/// from its first fields only, so that it is found in a status of any version: `None` for a
/// frame that fails its COBS or CRC check or holds anything else.
pub fn protocol_of_status(frame: &[u8]) -> Option<u16> {
    #[derive(Deserialize)]
    enum UplinkHead {
        Response {
            #[allow(dead_code)]
            request: u32,
            response: ResponseHead,
        },
    }
    #[derive(Deserialize)]
    enum ResponseHead {
        Status(u16),
    }
    let mut raw = [0u8; MAX_FRAME];
    let copy = raw.get_mut(..frame.len())?;
    copy.copy_from_slice(frame);
    let n = cobs::decode_in_place(copy)?;
    let (body, crc) = copy.get(..n)?.split_at(n.checked_sub(4)?);
    let mut expected = [0u8; 4];
    expected.copy_from_slice(crc);
    if CRC.checksum(body) != u32::from_le_bytes(expected) {
        return None;
    }
    match postcard::take_from_bytes::<Packet<UplinkHead>>(body) {
        Ok((
            Packet {
                body:
                    UplinkHead::Response {
                        response: ResponseHead::Status(protocol),
                        ..
                    },
                ..
            },
            _,
        )) => Some(protocol),
        Err(_) => None,
    }
}

/// Collects received bytes into frames (up to the 0x00 delimiter). A frame longer than
/// [`MAX_FRAME`] is dropped whole and reported once, at its delimiter.
#[derive(Clone, Debug)]
pub struct Decoder {
    buffer: heapless::Vec<u8, MAX_FRAME>,
    overflowed: bool,
}

impl Default for Decoder {
    fn default() -> Self {
        Self::new()
    }
}

impl Decoder {
    /// An empty decoder.
    pub const fn new() -> Self {
        Self {
            buffer: heapless::Vec::new(),
            overflowed: false,
        }
    }

    /// Takes one byte; at a delimiter, decodes the frame collected so far (an empty frame, e.g.
    /// a delimiter sent to resynchronise, gives `None`).
    pub fn push<T: DeserializeOwned>(
        &mut self,
        byte: u8,
    ) -> Option<Result<Packet<T>, DecodeError>> {
        if byte != 0 {
            if self.buffer.push(byte).is_err() {
                self.overflowed = true;
            }
            return None;
        }
        let result = if self.overflowed {
            Some(Err(DecodeError::TooLong))
        } else if self.buffer.is_empty() {
            None
        } else {
            Some(decode(&mut self.buffer))
        };
        self.buffer.clear();
        self.overflowed = false;
        result
    }
}

#[cfg(test)]
mod tests;
