"""The recorded file: topics and schemas, the record layer, the recorder, file recovery, the one drive reader."""
