import mmap

def change(image: mmap.mmap, offset: int, set_bits: int, clear_bits: int, toggle: int, /) -> int:
    """Set, clear, then toggle bits of the byte at ``offset``, atomically; the new value."""
