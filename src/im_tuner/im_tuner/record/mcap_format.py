"""MCAP v0 constants the library does not export lightly (https://mcap.dev/spec; the
opcodes are ``mcap.opcode.Opcode``): magic, the Message record's header size, the chunk
compressions this project writes. Pure: no numba."""

from __future__ import annotations

MAGIC = b'\x89MCAP0\r\n'
#: Bytes of a Message record before its payload: opcode u8, length u64, channel_id u16,
#: sequence u32, log_time u64, publish_time u64.
MESSAGE_HEADER_BYTES = 31
COMPRESSIONS = ('none', 'zstd', 'lz4')
