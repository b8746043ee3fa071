//! A mesh file's bytes in a request (`job.submit`'s `mesh_base64`): standard base64,
//! one definition for the client that encodes and the daemon that decodes.

use base64::Engine;

/// Decode standard base64 (RFC 4648, padding optional).
pub fn base64_decode(s: &str) -> Result<Vec<u8>, base64::DecodeError> {
    base64::engine::general_purpose::GeneralPurpose::new(
        &base64::alphabet::STANDARD,
        base64::engine::GeneralPurposeConfig::new()
            .with_decode_padding_mode(base64::engine::DecodePaddingMode::Indifferent),
    )
    .decode(s)
}

/// Encode standard base64 with padding.
pub fn base64_encode(b: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_round_trips() {
        for n in 0..20u8 {
            let v: Vec<u8> = (0..n).map(|i| i.wrapping_mul(37)).collect();
            assert_eq!(base64_decode(&base64_encode(&v)).unwrap(), v);
        }
        assert!(base64_decode("ab$c").is_err());
        assert_eq!(base64_decode("AQI").unwrap(), vec![1, 2]);
    }
}
