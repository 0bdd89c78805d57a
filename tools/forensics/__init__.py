"""Dataset forensics: is the data itself what it claims to be? See tools/README.md."""
