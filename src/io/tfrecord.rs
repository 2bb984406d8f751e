//! TFRecord framing: `u64 length (LE) | u32 masked CRC-32C of the length | payload | u32 masked
//! CRC-32C of the payload`, repeated to the end of the file.

use std::io::{Read, Write};

/// Records larger than this are refused: a corrupted length would otherwise allocate wildly.
pub const MAX_RECORD_BYTES: u64 = 1 << 30;

/// Why a TFRecord stream could not be read.
#[derive(Debug, thiserror::Error)]
pub enum TfRecordError {
    /// The underlying reader failed.
    #[error("record {record}: read failed: {source}")]
    Io {
        /// Index of the record being read.
        record: usize,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The file ended inside a record.
    #[error("record {record} at byte {offset}: file ends inside the {part}")]
    Truncated {
        /// Index of the record.
        record: usize,
        /// Byte offset where the record starts.
        offset: u64,
        /// Which part was cut short.
        part: &'static str,
    },
    /// The length's checksum does not match.
    #[error("record {record} at byte {offset}: length checksum mismatch (corrupted length)")]
    LengthCrc {
        /// Index of the record.
        record: usize,
        /// Byte offset where the record starts.
        offset: u64,
    },
    /// The payload's checksum does not match.
    #[error("record {record} at byte {offset}: payload checksum mismatch (corrupted data)")]
    DataCrc {
        /// Index of the record.
        record: usize,
        /// Byte offset where the record starts.
        offset: u64,
    },
    /// The length is implausibly large.
    #[error("record {record} at byte {offset}: length {len} exceeds {MAX_RECORD_BYTES} bytes")]
    TooLarge {
        /// Index of the record.
        record: usize,
        /// Byte offset where the record starts.
        offset: u64,
        /// The length read.
        len: u64,
    },
}

impl TfRecordError {
    /// Where the record starts (what `Display` prefixes with the record index).
    pub fn location(&self) -> String {
        match self {
            TfRecordError::Io { record, .. } => format!("record {record}"),
            TfRecordError::Truncated { record, offset, .. }
            | TfRecordError::LengthCrc { record, offset }
            | TfRecordError::DataCrc { record, offset }
            | TfRecordError::TooLarge { record, offset, .. } => {
                format!("record {record} at byte {offset}")
            }
        }
    }

    /// What is wrong, without the location.
    pub fn fault(&self) -> String {
        let full = self.to_string();
        let loc = self.location();
        full.strip_prefix(&loc)
            .and_then(|r| r.strip_prefix(": "))
            .map_or(full.clone(), str::to_string)
    }

    /// Index of the record the error is about.
    pub fn record(&self) -> usize {
        match self {
            TfRecordError::Io { record, .. }
            | TfRecordError::Truncated { record, .. }
            | TfRecordError::LengthCrc { record, .. }
            | TfRecordError::DataCrc { record, .. }
            | TfRecordError::TooLarge { record, .. } => *record,
        }
    }
}

/// CRC-32C (Castagnoli) of `data`, with the CPU's CRC32 instructions where it has them (SSE
/// 4.2, ARMv8): a table-driven loop checked half a gigabyte a second, half of the reading time
/// of a WOMD shard.
pub fn crc32c(data: &[u8]) -> u32 {
    ::crc32c::crc32c(data)
}

/// The masked CRC TFRecord stores (so that CRCs of CRCs stay well distributed).
pub fn masked_crc32c(data: &[u8]) -> u32 {
    let c = crc32c(data);
    (c.rotate_right(15)).wrapping_add(0xa282_ead8)
}

/// Reads records one by one, checking both checksums.
pub struct TfRecordReader<R> {
    inner: R,
    record: usize,
    offset: u64,
    failed: bool,
}

impl<R: Read> TfRecordReader<R> {
    /// Wraps a byte stream.
    pub fn new(inner: R) -> Self {
        Self {
            inner,
            record: 0,
            offset: 0,
            failed: false,
        }
    }

    /// Fills `buf`; `Ok(false)` when the stream ends before the first byte.
    fn fill(
        &mut self,
        buf: &mut [u8],
        part: &'static str,
        start: u64,
    ) -> Result<bool, TfRecordError> {
        let mut got = 0;
        while got < buf.len() {
            match self.inner.read(&mut buf[got..]) {
                Ok(0) if got == 0 && part == "length" => return Ok(false),
                Ok(0) => {
                    return Err(TfRecordError::Truncated {
                        record: self.record,
                        offset: start,
                        part,
                    })
                }
                Ok(n) => got += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(source) => {
                    return Err(TfRecordError::Io {
                        record: self.record,
                        source,
                    })
                }
            }
        }
        self.offset += buf.len() as u64;
        Ok(true)
    }

    fn read_record(&mut self) -> Result<Option<Vec<u8>>, TfRecordError> {
        let start = self.offset;
        let record = self.record;
        let mut len_buf = [0u8; 8];
        if !self.fill(&mut len_buf, "length", start)? {
            return Ok(None);
        }
        let mut crc_buf = [0u8; 4];
        self.fill(&mut crc_buf, "length checksum", start)?;
        if u32::from_le_bytes(crc_buf) != masked_crc32c(&len_buf) {
            return Err(TfRecordError::LengthCrc {
                record,
                offset: start,
            });
        }
        let len = u64::from_le_bytes(len_buf);
        if len > MAX_RECORD_BYTES {
            return Err(TfRecordError::TooLarge {
                record,
                offset: start,
                len,
            });
        }
        let mut data = vec![0u8; len as usize];
        self.fill(&mut data, "payload", start)?;
        self.fill(&mut crc_buf, "payload checksum", start)?;
        if u32::from_le_bytes(crc_buf) != masked_crc32c(&data) {
            return Err(TfRecordError::DataCrc {
                record,
                offset: start,
            });
        }
        self.record += 1;
        Ok(Some(data))
    }
}

impl<R: Read> Iterator for TfRecordReader<R> {
    type Item = Result<Vec<u8>, TfRecordError>;

    /// The next payload; after an error the iterator ends (framing cannot be recovered).
    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        match self.read_record() {
            Ok(Some(d)) => Some(Ok(d)),
            Ok(None) => None,
            Err(e) => {
                self.failed = true;
                Some(Err(e))
            }
        }
    }
}

/// Appends one framed record to `w`.
pub fn write_record(w: &mut impl Write, payload: &[u8]) -> std::io::Result<()> {
    let len = (payload.len() as u64).to_le_bytes();
    w.write_all(&len)?;
    w.write_all(&masked_crc32c(&len).to_le_bytes())?;
    w.write_all(payload)?;
    w.write_all(&masked_crc32c(payload).to_le_bytes())
}

/// Frames `payloads` as one TFRecord byte stream.
pub fn frame_records<P: AsRef<[u8]>>(payloads: &[P]) -> Vec<u8> {
    let mut buf = Vec::new();
    for p in payloads {
        write_record(&mut buf, p.as_ref()).expect("writing to memory cannot fail");
    }
    buf
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32c_matches_the_bitwise_definition_at_every_length_and_alignment() {
        let bitwise = |data: &[u8]| {
            let mut c = !0u32;
            for &b in data {
                c ^= b as u32;
                for _ in 0..8 {
                    c = if c & 1 != 0 {
                        0x82F6_3B78 ^ (c >> 1)
                    } else {
                        c >> 1
                    };
                }
            }
            !c
        };
        let data: Vec<u8> = (0..4099u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
            .collect();
        for start in 0..9 {
            for len in (0..300).chain([1024, 4090 - start]) {
                let d = &data[start..start + len];
                assert_eq!(crc32c(d), bitwise(d), "start {start}, length {len}");
            }
        }
    }

    #[test]
    fn crc32c_known_vector() {
        assert_eq!(crc32c(b"123456789"), 0xE306_9283);
        assert_eq!(crc32c(b""), 0);
    }

    #[test]
    fn round_trip() {
        let buf = frame_records::<&[u8]>(&[b"hello", b"", b"world!"]);
        let got: Vec<Vec<u8>> = TfRecordReader::new(&buf[..]).map(Result::unwrap).collect();
        assert_eq!(got, vec![b"hello".to_vec(), vec![], b"world!".to_vec()]);
    }

    #[test]
    fn truncation_names_the_record() {
        let buf = frame_records::<&[u8]>(&[b"first", b"second record"]);
        for cut in 1..buf.len() {
            if cut == 8 + 4 + 5 + 4 {
                continue; // exactly one whole record
            }
            let results: Vec<_> = TfRecordReader::new(&buf[..cut]).collect();
            let err = results.last().unwrap().as_ref().unwrap_err();
            let expected = if cut < 21 { 0 } else { 1 };
            assert_eq!(err.record(), expected, "cut at {cut}");
            assert!(matches!(err, TfRecordError::Truncated { .. }));
        }
    }

    #[test]
    fn bit_flips_are_detected() {
        let buf = frame_records::<&[u8]>(&[b"first", b"second record"]);
        for byte in 0..buf.len() {
            let mut bad = buf.clone();
            bad[byte] ^= 0x10;
            let results: Vec<_> = TfRecordReader::new(&bad[..]).collect();
            let err = results
                .iter()
                .find_map(|r| r.as_ref().err())
                .unwrap_or_else(|| panic!("flip at byte {byte} went unnoticed"));
            assert_eq!(err.record(), if byte < 21 { 0 } else { 1 });
        }
    }
}
