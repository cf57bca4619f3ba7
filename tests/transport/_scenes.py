"""Scenes with published reference values, shared by the transport tests.

Sources: van de Hulst (1980) and Giovanelli (1955), as quoted by Wang, Jacques & Zheng (1995, MCML);
the citations are in tissuefit/data/SOURCES.md.
"""

import math

import tissuefit as tf

INF = math.inf


def van_de_hulst() -> tf.Scene:
    """Slab of optical thickness 2 (0.02 cm), matched boundaries, albedo 0.9, g = 0.75.
    Published: Rd = 0.09739, Tt = 0.66096 (5 digits)."""
    return tf.Scene(tf.LayeredTissue(n=[1.0], mua=[10.0], mus=[90.0], g=[0.75], thickness=[0.02]))


VAN_DE_HULST = {"rd": 0.09739, "tt": 0.66096, "precision": 0.5e-5}


def giovanelli(n: float = 1.0) -> tf.Scene:
    """Semi-infinite medium, albedo 0.9, g = 0, index n under air (n = 1: matched)."""
    return tf.Scene(tf.LayeredTissue(n=[n], mua=[10.0], mus=[90.0], g=[0.0], thickness=[INF]))


GIOVANELLI = {"rd_matched": 0.41495, "precision_matched": 0.5e-5, "total_n15": 0.2600, "precision_n15": 0.5e-4}


def three_layer() -> tf.Scene:
    """Glass on top of two turbid layers with mismatched indices (bookkeeping stress case)."""
    return tf.Scene(
        tf.LayeredTissue(
            n=[1.5, 1.37, 1.45], mua=[0.0, 1.0, 2.0], mus=[0.0, 100.0, 10.0], g=[0.0, 0.9, 0.0],
            thickness=[0.1, 0.1, 0.2], n_above=1.0, n_below=1.0,
        )
    )
