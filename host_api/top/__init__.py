"""``cifemu top``: a live view of one card for a terminal (Textual), or one snapshot (Rich)."""
