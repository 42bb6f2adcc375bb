"""Label library of the `label` stage: contact sets (:mod:`.contacts`) and labelled tables (:mod:`.table`)."""
