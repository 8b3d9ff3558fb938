"""The exam in the hospital's archive (PACS): DICOM objects of the captures and measurements
(:mod:`.objects`), the patient and study they belong to (:mod:`.exam`), a store-and-forward
queue on disk (:mod:`.queue`) sent by C-STORE or STOW-RS (:mod:`.send`, :mod:`.forwarder`),
the department's Modality Worklist (:mod:`.worklist`). docs/archive.md says why each choice.

Patient identity lives only in the DICOM objects and the queue's folder: never in logs, the
session recording, the stats or a page's URL."""
