// Foxglove's own JSON schemas, as the @foxglove/schemas package publishes them: the standard the logger's topics
// that carry a Foxglove schema name (foxglove.LocationFix: /gnss/fix and /nav/fix) are checked against
// (tests/test_mcap_js.py), beside the schema each file embeds.
//
//   npm ci --prefix tools/mcap_js && node tools/mcap_js/foxglove_schema.mjs LocationFix [NAME...]
//
// Prints ONE JSON line: {NAME: schema, ...}; a name the package does not have is one line on stderr, exit 1.
import { createRequire } from "node:module";

const schemas = createRequire(import.meta.url)("@foxglove/schemas/jsonschema");
const out = {};
for (const name of process.argv.slice(2)) {
  if (!(name in schemas)) {
    process.stderr.write(`foxglove_schema.mjs: @foxglove/schemas has no schema ${name}\n`);
    process.exit(1);
  }
  out[name] = schemas[name];
}
process.stdout.write(JSON.stringify(out) + "\n");
