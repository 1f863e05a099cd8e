"""Synthetic meshes with known answers: the procedural face and ball (``phantom``), the face
re-meshed with other cell types (``face_variants``), a small mixed-element bar (``mixed_bar``) and
the face with its bones apart from the tissue (``off_bone``). The tests, benchmarks and examples
build on them; no patient data exists here."""
