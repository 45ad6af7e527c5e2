"""Rendered knowledge that inspection compares against: the reference sub-images of a healthy lens and
the signature table of each error type, both built by the tracer and cached by a content key."""

from mlaqc.lazy import lazy_exports

_EXPORTS = {
    "ReferenceModel": "reference", "reference_model": "reference", "build_reference": "reference",
    "SignatureTable": "signatures", "SignatureSet": "signatures", "signature_table": "signatures",
    "build_signatures": "signatures", "build_signature_set": "signatures",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
