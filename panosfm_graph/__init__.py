"""panosfm: panoramic structure from motion via geometric relationship detection.

Implements Ikehata, Furukawa, Boyadzhiev and Shan, *Panoramic Structure from
Motion via Geometric Relationship Detection*. See README.md for the pipeline.
"""
__version__ = "0.1.0"
