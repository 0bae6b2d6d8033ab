"""Values from outside (a scene file, --set, a browser) quoted in messages at bounded length and cost."""
import reprlib

QUOTE_CHARS = 40  # of a value from outside quoted in a message: a scene, --set or a browser can send megabytes
_QUOTE = reprlib.Repr()
_QUOTE.maxlevel, _QUOTE.maxstring, _QUOTE.maxother = 3, QUOTE_CHARS, QUOTE_CHARS  # a nested value costs little to quote


def quote(value) -> str:
    """repr(value) cut to at most QUOTE_CHARS characters, at bounded cost whatever the value's size."""
    try:
        text = _QUOTE.repr(value)
    except ValueError:  # an int of more than sys.get_int_max_str_digits() digits
        text = f"<an integer of {value.bit_length()} bits>"
    return text if len(text) <= QUOTE_CHARS else text[: QUOTE_CHARS - 3] + "..."
