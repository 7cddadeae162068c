"""Records: the sessions database, reports and the study statistics."""
