"""Light-field decoding with the array's measured errors (issue #41)."""
