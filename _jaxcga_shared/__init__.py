"""The shared internal layer of the jaxcga distribution, below every package (``_jaxcga_shared`` <- ``jaxcga`` <-
``deform`` <- ``cutting``; ``_jaxcga_shared`` <- ``xfem``): argument checks (``checks``), host machinery and the host
call (``host``), output files that survive failure and checks of paths (``output``), mesh utilities (``mesh``),
reading mesh files (``meshfile``), batches split over devices (``devices``), kernels with a CPU and a GPU
formulation (``platform``), explicit rank promotion (``broadcast``), the browser viewer (``viewer``, re-exported as
``deform.view``). Nothing here is public API: the leading underscore of the package says so, as ``_pytest`` does for
pytest, and its modules import nothing of the packages above."""
