"""Secrets out of everything printed: a password in a URL is shown as ``***``.

Every URL the user gives (``--mqtt``, ``--robot-mqtt``, a broker's address in
an error) goes through :func:`mask_url` before it is printed or logged, and
every line a verb refuses with goes through :func:`redact`, which masks any
``scheme://user:password@`` in free text (an exception's message may quote
the URL it was given). docs/security.md, "Secrets in output".
"""

from __future__ import annotations

import re

# scheme://user:password@ -- the password up to the last "@" of the token, so
# that an unencoded "@" in it is masked too.
_CREDENTIALS = re.compile(r"(?P<head>[A-Za-z][A-Za-z0-9+.-]*://[^:/@\s'\"]*):[^\s'\"]*@")


def redact(text: str) -> str:
    """``text`` with the password of every URL in it replaced by ``***``."""
    return _CREDENTIALS.sub(r"\g<head>:***@", text)


def mask_url(url: str) -> str:
    """``url`` with its password replaced by ``***`` (for output, logs and summaries)."""
    return redact(url)
