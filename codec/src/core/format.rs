//! What a reader finds wrong with coded bytes, by kind: every codec's headers and streams (plane
//! codecs, volumes, curves) and the shared pieces they are built of answer this type, so that a
//! caller tells a header that contradicts itself from a stream that does not decode without
//! reading a message. The container names the plane, the chunk and the file around it
//! ([`crate::Error::asset`]).

/// A header or a stream that no encoder of this crate writes. The message is for people.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FormatError {
    /// The header contradicts itself or the asset's metadata (sizes, levels, steps).
    #[error("{0}")]
    Header(String),
    /// The stream is truncated or corrupt, or decodes to parameters no operator takes.
    #[error("{0}")]
    Stream(String),
}

impl FormatError {
    /// A [`FormatError::Header`] saying `message`.
    pub fn header(message: impl Into<String>) -> FormatError {
        FormatError::Header(message.into())
    }

    /// A [`FormatError::Stream`] saying `message`.
    pub fn stream(message: impl Into<String>) -> FormatError {
        FormatError::Stream(message.into())
    }
}
