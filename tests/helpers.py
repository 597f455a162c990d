"""Small assertions shared by the test modules."""

import pytest

from seqvpr.errors import SeqvprError


def raises_one_line(match: str, fn, *args, **kwargs) -> str:
    """Call fn, expect a SeqvprError whose message is one line containing ``match``; return the message."""
    with pytest.raises(SeqvprError) as info:
        fn(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    assert match in message
    return message
