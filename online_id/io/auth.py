"""Authenticated command frames, SecOC-like: a truncated HMAC-SHA256 over ID, payload and freshness value.

AUTOSAR SecOC authenticates a frame with a MAC over its data ID, its
payload and a freshness value both sides keep, truncated to what the frame
has room for. Here (see the DBC's ``OidCommand`` and ``docs/security.md``):

* the MAC is HMAC-SHA256 (RFC 2104, FIPS 198-1) truncated to its first
  4 bytes (NIST SP 800-107 allows truncation; 32 bits against the 16 wrong
  MACs a minute the service lets through, :mod:`online_id.service.commands`, leave a
  forger one chance in 2^32 per try, 500 years of trying for an even chance);
  chosen over AES-CMAC because Python's standard library has it (no
  dependency on a crypto package) and every PLC or bench PC language can
  compute it;
* the message authenticated is the frame's arbitration ID (4 bytes,
  big-endian), the command byte and the full 32-bit freshness value
  (4 bytes, big-endian): 9 bytes;
* the key is 16 to 64 bytes, written as hex in a file; a relative file name
  is looked up in ``$CREDENTIALS_DIRECTORY`` (systemd's ``LoadCredential=``).
"""

from __future__ import annotations

import hashlib
import hmac
import os
from pathlib import Path

from online_id.errors import ConfigError

ALGORITHM = "HMAC-SHA256"
MIN_KEY_BYTES = 16
MAX_KEY_BYTES = 64


def credential_path(name: str) -> Path:
    """``name`` as given when absolute, else in ``$CREDENTIALS_DIRECTORY`` when systemd set it."""
    path = Path(name)
    creds = os.environ.get("CREDENTIALS_DIRECTORY")
    if not path.is_absolute() and creds:
        path = Path(creds) / path
    return path


def read_key(name: str, key: str = "commands.key_file") -> bytes:
    """The key in file ``name`` (hex digits; blanks and line ends ignored); one-line errors naming ``key``."""
    path = credential_path(name)
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{key}: cannot read the key {path}: {getattr(err, 'strerror', None) or err}") from None
    digits = "".join(text.split())
    try:
        secret = bytes.fromhex(digits)
    except ValueError:
        raise ConfigError(f"{key}: {path} must hold the key as hex digits (e.g. from `openssl rand -hex 32`)") \
            from None
    if not MIN_KEY_BYTES <= len(secret) <= MAX_KEY_BYTES:
        raise ConfigError(f"{key}: {path} holds a key of {len(secret)} bytes, expected {MIN_KEY_BYTES} to "
                          f"{MAX_KEY_BYTES} (`openssl rand -hex 32` gives 32)")
    return secret


def command_mac(secret: bytes, arbitration_id: int, command: int, freshness: int, n_bytes: int = 4) -> bytes:
    """The first ``n_bytes`` of HMAC-SHA256(secret, ID | command | freshness) (see module notes)."""
    message = (int(arbitration_id).to_bytes(4, "big") + bytes([int(command) & 0xFF])
               + (int(freshness) & 0xFFFFFFFF).to_bytes(4, "big"))
    return hmac.new(secret, message, hashlib.sha256).digest()[:n_bytes]


def mac_matches(secret: bytes, arbitration_id: int, command: int, freshness: int, mac: bytes) -> bool:
    """True when ``mac`` is the truncated MAC of the frame (compared in constant time)."""
    return hmac.compare_digest(command_mac(secret, arbitration_id, command, freshness, len(mac)), mac)
