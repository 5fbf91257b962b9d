"""Online estimators (pure numpy, no I/O): AFFRLS, LPSO and their fusion, vectorised over cells."""
