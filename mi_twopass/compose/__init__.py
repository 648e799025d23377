"""``twopass``'s parts: the pilot that measures candidate estimators on a scene
(:mod:`.pilot`) and the cost model that chooses among them (:mod:`.cost`)."""
