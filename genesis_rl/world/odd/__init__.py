"""Natural edge cases: the operational design domain (``domain``), the physical conditions a weather makes
(``conditions``), and how fast weather may change and how likely a trajectory is (``dynamics``)."""
