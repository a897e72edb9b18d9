"""`hpgs suggest`: where to take the next photos, for a capture in progress.

Every selector needs only a pose and the current splat, none the candidate's photo, so the same scores rank poses
no one has photographed yet: `candidates` builds them (orbit rings, a Fibonacci sphere, or a camera path) and drops
the unusable ones, `command` scores them with a selector and writes the answer, `figures` draws it.
"""
