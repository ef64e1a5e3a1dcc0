"""Files canical writes: atomically (:mod:`atomic_file`), to a plan of outputs checked before any
work starts (:mod:`output_plan`), YAML read with its limits (:mod:`yaml_text`) and the
signing keys' files (:mod:`key_file`)."""

# The package's public face (tests/test_rings.py keeps it equal to what other rings import).
__all__ = ["atomic_file", "key_file", "output_plan", "yaml_text"]
