"""artdef core: articulated deformation from displacement fields (Lang, Pai & Seidel, GI 2003).

Plain numpy/scipy, no ``bpy``. The Blender layer (``operators/``, ``panels/``) is a thin shell
around these functions:

>>> from artdef_addon import samples, fit
>>> result = fit.fit(samples.make("rod"), links=3)
"""
__all__ = ["scan", "fit", "model", "samples", "metric", "clustering", "merge", "joints", "skinning",
           "frames", "quality"]
