"""The procedures: one subpackage per layer, each importing only those below it (docs/architecture.md).

``cli`` (the ``instrument`` command line) and ``serve`` (the web view, OPC UA) are the faces; ``engine``
runs any procedure kind; ``report`` shows runs; ``kinds`` holds the procedure kinds by family; ``store``
keeps runs and their typed samples; ``station`` is the station and what everything above shares.
``demo`` runs the calibrations and the ISO cycle on the simulated cell. This package itself exports
nothing: import from the subpackage that offers a name.
"""
