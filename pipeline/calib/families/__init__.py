"""The model families: one module each, every module here with a ``FAMILY`` is one (found by
`pipeline.calib.registry.families`; a family from elsewhere is added with `pipeline.calib.registry.register`).

A family (`pipeline.calib.families.base.Family`) is its name, rank, colour and title and the hooks that
training (`pipeline.calib.fitting.fit_fold`), cross-validation, scoring, the export
(`pipeline.export.trained.read_group`) and the deployment tests (`pipeline.deploy.models.group_models`)
call; the pages and the metrics iterate the registry. The closed-form families share
`pipeline.calib.families.closed_form`.
"""
