"""jaxcga_cli: the ``jaxcga`` command line, the application above the library packages (``jaxcga``, ``deform``,
``cutting``, ``xfem``), which it uses through their public APIs only.

One module per subcommand (``demo``, ``skin``, ``animate``, ``fit``, ``cut``, ``tear``, ``drill``, ``deform``,
``arap``, ``fem``, ``xfem``, ``view``), run by ``main``; what they share: ``arguments`` (options and enumerations),
``models`` (loading models and meshes, the bounding box, the motion and the ``--handles`` file of ``deform`` and
``arap``), ``output`` (suffixes and the one writer chosen by suffix),
``figures`` (matplotlib, set up once), ``report`` (status lines, progress bars, one-line errors on stderr) and
``cache`` (JAX's persistent compilation cache in the user's cache directory, turned on by ``main``).
"""
