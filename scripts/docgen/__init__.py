"""The page builders of ``scripts/gen_docs.py``, one module per reference page (or pair of
pages), on shared Markdown helpers (:mod:`docgen.markdown`)."""
