"""Data samples on the bus: msgpack maps of a data type's fields (docs/protocol.md, 4)."""

from __future__ import annotations

from typing import Any

import msgspec


def _enc_hook(obj: Any) -> Any:
    """Let nodes publish numpy arrays and scalars without importing numpy here."""
    if hasattr(obj, "tolist"):
        return obj.tolist()
    raise NotImplementedError(f"cannot encode {type(obj).__name__}")


#: The one encoder and decoder of data samples (reused: no per-sample set-up).
DATA_ENCODER = msgspec.msgpack.Encoder(enc_hook=_enc_hook)
DATA_DECODER = msgspec.msgpack.Decoder()


def encode_data(data: Any) -> bytes:
    return DATA_ENCODER.encode(data)


def decode_data(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Decode a data sample; raise ValueError if it is not a msgpack map."""
    try:
        value = DATA_DECODER.decode(payload)
    except msgspec.DecodeError as e:
        raise ValueError(f"not msgpack: {e}") from None
    if not isinstance(value, dict):
        raise ValueError(f"a data sample must be a map, got {type(value).__name__}")
    return value
