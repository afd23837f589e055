"""MCAP v0 constants (https://mcap.dev/spec): magic, record opcodes, the Message record's
header size, the chunk compressions this project writes. Pure: the writer, the reader,
the repair and the schema texts share them without importing numba."""

from __future__ import annotations

MAGIC = b'\x89MCAP0\r\n'
OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_ATTACHMENT = 0x09
OP_ATTACHMENT_INDEX = 0x0A
OP_STATISTICS = 0x0B
OP_METADATA = 0x0C
OP_METADATA_INDEX = 0x0D
OP_SUMMARY_OFFSET = 0x0E
OP_DATA_END = 0x0F

#: Bytes of a Message record before its payload: opcode u8, length u64, channel_id u16,
#: sequence u32, log_time u64, publish_time u64.
MESSAGE_HEADER_BYTES = 31
COMPRESSIONS = ('none', 'zstd', 'lz4')
