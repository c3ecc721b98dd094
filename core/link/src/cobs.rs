//! Consistent Overhead Byte Stuffing (Cheshire and Baker, IEEE/ACM Trans. Networking 7(2), 1999):
//! the data is cut at each 0x00 into blocks of at most 254 non-zero bytes, each written as
//! `len + 1` followed by its bytes, so the encoded data holds no 0x00 and grows by at most one byte
//! per 254. Without the delimiter (the caller appends it).

/// Encodes `data` into `out`; the encoded length, or `None` if `out` is too short.
pub(crate) fn encode(data: &[u8], out: &mut [u8]) -> Option<usize> {
    let mut code_at = 0;
    let mut write = 1;
    let mut code: u8 = 1;
    *out.get_mut(code_at)? = 0;
    for &byte in data {
        if byte == 0 {
            *out.get_mut(code_at)? = code;
            code_at = write;
            write += 1;
            code = 1;
            *out.get_mut(code_at)? = 0;
        } else {
            *out.get_mut(write)? = byte;
            write += 1;
            code += 1;
            if code == 0xff {
                *out.get_mut(code_at)? = code;
                code_at = write;
                write += 1;
                code = 1;
                *out.get_mut(code_at)? = 0;
            }
        }
    }
    *out.get_mut(code_at)? = code;
    Some(write)
}

/// Decodes `buf` in place; the decoded length, or `None` if it holds a 0x00 or a block runs past
/// its end.
pub(crate) fn decode_in_place(buf: &mut [u8]) -> Option<usize> {
    let mut read = 0;
    let mut write = 0;
    while read < buf.len() {
        let code = *buf.get(read)?;
        if code == 0 {
            return None;
        }
        read += 1;
        let end = read + usize::from(code) - 1;
        if end > buf.len() {
            return None;
        }
        while read < end {
            let byte = *buf.get(read)?;
            if byte == 0 {
                return None;
            }
            *buf.get_mut(write)? = byte;
            write += 1;
            read += 1;
        }
        if code != 0xff && read < buf.len() {
            *buf.get_mut(write)? = 0;
            write += 1;
        }
    }
    Some(write)
}
