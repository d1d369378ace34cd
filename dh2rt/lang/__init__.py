"""The DH2 language: AST, text parser, Python builder API and program images.

Text (``.dh2``) and the Python API (:mod:`dh2rt.lang.api`) build the same frozen AST
(:mod:`dh2rt.lang.ast`); :mod:`dh2rt.compiler` turns it into closures once.
"""
